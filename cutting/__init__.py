"""cutting: cut, tear and drill of skinned triangle meshes (cut/tear/drill paper, sec. 4.2-4.3).

Topology changes run on the host in vectorized numpy and return new arrays; the geometric
predicates can run on the jaxcga kernel (``predicates="ga"``). Where things live: ``_cut``
(Algorithm 1, capping), ``_weights`` (weights of new vertices, sec. 4.3), ``_predicates`` (Table 1's
Euclidean and GA predicates).
"""

from cutting._cut import MeshEdges, PlaneCut, cut, cut_positions, mesh_edges, plane_cut
from cutting._predicates import PREDICATES
from cutting._weights import blend_weights

__all__ = ["PREDICATES", "MeshEdges", "PlaneCut", "blend_weights", "cut", "cut_positions", "mesh_edges", "plane_cut"]
