"""cutting: cut, tear and drill of skinned triangle meshes (cut/tear/drill paper, sec. 4.2-4.3).

Topology changes run on the host in vectorized numpy and return new arrays; the geometric
predicates can run on the jaxcga kernel (``predicates="ga"``). Where things live: ``_cut``
(Algorithm 1, capping), ``_tear`` (Algorithm 2), ``_drill`` (Algorithm 3, eq. 18-20), ``_weights``
(weights of new vertices, sec. 4.3), ``_predicates`` (Table 1's Euclidean and GA predicates),
``_geometry`` (what the three share: adjacency, poses, segment hits, triangulating the pieces of a face).
"""

from cutting._cut import PlaneCut, cut, cut_positions, plane_cut
from cutting._drill import Drilling, drill, drill_mesh, drill_positions, refine
from cutting._geometry import MeshEdges, mesh_edges
from cutting._predicates import PREDICATES
from cutting._tear import TearPath, scalpel_path, tear, tear_path, tear_positions
from cutting._weights import blend_weights

__all__ = ["PREDICATES", "Drilling", "MeshEdges", "PlaneCut", "TearPath", "blend_weights", "cut", "cut_positions",
           "drill", "drill_mesh", "drill_positions", "mesh_edges", "plane_cut", "refine", "scalpel_path", "tear",
           "tear_path", "tear_positions"]
