r"""The physics study's command line: learn LCSs of a MuJoCo cart-pole with two soft walls.

The plant and its data are :mod:`studies.physics.plant`, the study :mod:`studies.physics.study`,
its report :mod:`studies.physics.report`; this module re-exports their public names (and is the
``module`` of the study configs). Run it with::

    python -m studies.physics.cartpole_walls --config studies/configs/physics_cartpole.toml \
        --out studies/results/physics [--workers 2] [--scheduler tcp://host:8786]

or ``lcs-cvx study run studies/configs/physics_cartpole.toml --out studies/results/physics``.
Running the same command again reuses the training jobs finished in ``<out>/studies.sqlite``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tomllib

from .plant import STATE_NAMES as STATE_NAMES
from .plant import STATE_UNITS as STATE_UNITS
from .plant import WALLS as WALLS
from .plant import CartPoleWalls as CartPoleWalls
from .plant import Physics as Physics
from .plant import Sampling as Sampling
from .plant import Transitions as Transitions
from .plant import mjcf as mjcf
from .plant import sample_transitions as sample_transitions
from .study import CONFIG_SECTIONS as CONFIG_SECTIONS
from .study import parse_config as parse_config
from .study import run_study as run_study

__all__ = [
    "Physics",
    "Sampling",
    "Transitions",
    "CartPoleWalls",
    "mjcf",
    "sample_transitions",
    "parse_config",
    "run_study",
    "main",
]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Cart-pole with soft walls (MuJoCo): learn LCSs and baselines.")
    ap.add_argument("--config", required=True, help="TOML config (studies/configs/physics_cartpole.toml)")
    ap.add_argument("--out", required=True, help="output directory (e.g. studies/results/physics)")
    ap.add_argument("--workers", type=int, default=2,
                    help="training processes (default 2; 1: in this process)")
    ap.add_argument("--scheduler", default=None, metavar="ADDRESS",
                    help="run the training jobs on Dask: 'local' (a LocalCluster of --workers "
                    "processes) or a scheduler address tcp://host:8786 (default: local processes)")
    ap.add_argument("--seeds", type=int, nargs="+", default=None,
                    help="the LCS fits' seeds instead of the config's [lcs] seeds (another draw of the study's "
                         "restarts, for the spread of what it chose)")
    ap.add_argument("--losses", nargs="+", default=None, help="the LCS losses instead of the config's")
    args = ap.parse_args(argv)
    with open(args.config, "rb") as f:
        config = tomllib.load(f)
    config.setdefault("name", os.path.splitext(os.path.basename(args.config))[0])
    for key, value in (("seeds", args.seeds), ("losses", args.losses)):
        if value is not None:
            config.setdefault("lcs", {})[key] = value
    run_study(config, args.out, args.workers, scheduler=args.scheduler)
    return 0


if __name__ == "__main__":
    sys.exit(main())
