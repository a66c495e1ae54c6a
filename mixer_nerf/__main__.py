"""``python -m mixer_nerf`` is the ``mixer-nerf`` command."""

import sys

from .cli import main

sys.exit(main())
