"""Config-driven studies of the paper's Fig. 1 (Sec. 5.1, panels (a)-(e)).

- :mod:`~lcs_cvx.study.config` -- the TOML configs (``studies/configs/``), checked.
- :mod:`~lcs_cvx.study.cells` -- the grid (swept value x trial x method), seeds, one cell's work.
- :mod:`~lcs_cvx.study.store` -- the SQLite results store (the client writes it, per cell).
- :mod:`~lcs_cvx.study.batched_cells` -- cells that differ only in their seeds, trained together.
- :mod:`~lcs_cvx.study.executors` -- local process pool, Dask distributed cluster, or this process.
- :mod:`~lcs_cvx.study.runner` -- ``lcs-cvx study run``: resume, skip finished cells.
- :mod:`~lcs_cvx.study.report` -- ``lcs-cvx study report``: figures and tables with anchors.
- :mod:`~lcs_cvx.study.baselines` -- methods besides the losses: affine, MLP, PARC.
- :mod:`~lcs_cvx.study.limits` -- a cell's time limit: a child process killed at the limit.
"""

from .cells import cell_seeds as cell_seeds
from .cells import expand as expand
from .cells import run_cell as run_cell
from .config import config_hash as config_hash
from .config import load_config as load_config
from .report import report as report
from .runner import RunSummary as RunSummary
from .runner import StudyError as StudyError
from .runner import run_config as run_config
from .store import Store as Store

__all__ = [
    "RunSummary",
    "Store",
    "StudyError",
    "cell_seeds",
    "config_hash",
    "expand",
    "load_config",
    "report",
    "run_cell",
    "run_config",
]
