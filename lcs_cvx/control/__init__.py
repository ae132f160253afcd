"""Control with an LCS: C3, consensus complementarity control (model-predictive control by ADMM
between a QP over the horizon and a projection onto the complementarity set of eq. (1))."""

from .c3 import C3 as C3
from .costs import Horizon as Horizon
from .costs import Layout as Layout
from .costs import dare as dare
from .examples import CartpoleProblem as CartpoleProblem
from .examples import c3_cartpole as c3_cartpole
from .plan import Plan as Plan
from .projection import project_enumerate as project_enumerate
from .qp import Bounds as Bounds
from .qp import qp_problem as qp_problem
from .relearn import Relearning as Relearning
from .relearn import Round as Round
from .relearn import relearn as relearn
from .simulation import ClosedLoop as ClosedLoop
from .simulation import closed_loop as closed_loop

__all__ = ["C3", "Plan", "ClosedLoop", "closed_loop", "dare", "CartpoleProblem", "c3_cartpole",
           "project_enumerate", "qp_problem", "Horizon", "Layout", "Bounds", "relearn", "Relearning", "Round"]
