"""Training Mixer-NeRF: configuration, the training loop, checkpoints and logs.

    from mixer_nerf.train import TrainConfig, Trainer
    summary = Trainer(TrainConfig(data="path/to/lego", out="runs/lego")).fit()

A run folder holds ``checkpoint.pt`` (atomic, every ``ckpt_every`` steps and at the end),
``config.json``, ``train_log.csv``, ``val_log.csv``, ``curves.png``, ``summary.json`` and, with
``tensorboard=True``, ``tensorboard/``.

Names are imported lazily, so that ``mixer_nerf.train.config`` (used to parse the command line)
does not pull in torch, the model and the renderer.
"""

from importlib import import_module

_EXPORTS = {
    "CheckpointError": "checkpoint",
    "load_checkpoint": "checkpoint",
    "save_checkpoint": "checkpoint",
    "DEMO_SETTINGS": "config",
    "TrainConfig": "config",
    "NonFiniteError": "guard",
    "OutputError": "output",
    "RunFiles": "output",
    "TrainedRun": "restore",
    "load_trained": "restore",
    "Trainer": "trainer",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
