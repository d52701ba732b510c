"""softbody: stiffness-warped finite elements (tet4, hex8, tet10) with implicit integration.

The FEM core: numpy and scipy only (pybullet and rerun live in the ``integration`` package).
"""
from .body import MODELS, FemBody
from .elements import ELEMENT_TYPES, ElementType, element_type
from .equilibrium import solve_equilibrium
from .linearisation import LinearisationWarning
from .locking import LockingWarning
from .fibres import Fibres
from .errors import InvalidInputError, MeshError, SimulationDiverged, SolverError
from .integrator import Constraints
from .material import LinearElastic, Regions
from .mesh import Mesh
from .meshing import ball_mesh, box_mesh, read_mesh, to_tet10, tube_mesh
from .simulation import Simulation, solve_static
from .stack import BodyStack, stack_key
from .state import SimulationState
from .surface import tetrahedralize

__all__ = [
    "BodyStack", "stack_key",
    "Constraints", "ELEMENT_TYPES", "MODELS", "ElementType", "FemBody", "Fibres", "InvalidInputError", "LinearElastic", "Regions", "LinearisationWarning", "LockingWarning", "Mesh",
    "MeshError", "Simulation", "SimulationDiverged", "SimulationState", "SolverError", "ball_mesh", "box_mesh", "element_type", "read_mesh",
    "solve_equilibrium", "solve_static", "tetrahedralize", "to_tet10", "tube_mesh",
]
__version__ = "0.1.0"
