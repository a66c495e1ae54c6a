"""A Blender scene that trains on every K-th training view of another, for generalisation screens.

    python tools/subset_views.py .data/lego_400 .data/lego25 --every 4

Writes ``OUT/transforms_train.json`` with every ``--every``-th training frame (from the first) and
copies the other splits' transforms files as they are; every ``file_path`` points at the source
scene's images, so nothing is copied but the JSON. The held-out views stay the source's.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path


def subset_views(source: Path, out: Path, every: int) -> int:
    """Write the subset scene into ``out``; returns the number of training views kept."""
    if every < 1:
        raise ValueError(f"--every must be >= 1, got {every}")
    splits = sorted(source.glob("transforms_*.json"))
    if not any(path.name == "transforms_train.json" for path in splits):
        raise FileNotFoundError(f"{source}: no transforms_train.json (not a Blender scene)")
    out.mkdir(parents=True, exist_ok=True)
    to_source = Path(os.path.relpath(source.resolve(), out.resolve()))
    kept = {}
    for path in splits:
        meta = json.loads(path.read_text())
        frames = meta["frames"][::every] if path.name == "transforms_train.json" else meta["frames"]
        meta["frames"] = [{**frame, "file_path": str(to_source / frame["file_path"])} for frame in frames]
        (out / path.name).write_text(json.dumps(meta, indent=1))
        kept[path.name] = len(frames)
    return kept["transforms_train.json"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("source", type=Path, help="a Blender scene folder")
    parser.add_argument("out", type=Path, help="the subset scene's folder")
    parser.add_argument("--every", type=int, default=4, help="keep every K-th training view (default 4)")
    args = parser.parse_args()
    kept = subset_views(args.source, args.out, args.every)
    print(f"{args.out}: {kept} training views of {args.source}, its held-out views as they are")


if __name__ == "__main__":
    main()
