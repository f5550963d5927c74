"""cutting: cut, tear and drill of skinned triangle meshes (cut/tear/drill paper, sec. 4.2-4.3).

One convention for the three tools: the tool is a value (``Plane``, ``Scalpel``, ``Drill``);
``X_topology(V, F, tool)`` computes the topology change on the host (``CutTopology``,
``TearTopology``, ``DrillTopology``); ``cut`` / ``tear`` / ``drill(mesh, tool, *, return_topology=False)``
apply it to a SkinnedMesh; ``X_positions(V, topology, tool)`` are the new vertices as a JAX function of
the vertices and the tool, differentiable for a fixed topology.

Topology changes run on the host in vectorized numpy and return new arrays; the geometric
predicates are the paper's GA ones by default (``predicates="ga"``, from the jaxcga kernel's product
tables) or Euclidean (``predicates="euclidean"``), Table 1. Where things live: ``_tools`` (the tool
values), ``_cut`` (Algorithm 1, capping), ``_tear`` (Algorithm 2), ``_drill`` (Algorithm 3, eq. 18-20),
``_weights`` (weights of new vertices, sec. 4.3), ``_predicates`` (Table 1's Euclidean and GA predicates),
``_geometry`` (what the three share: adjacency, poses, segment hits, triangulating the pieces of a face).
"""

from cutting._cut import CutTopology, cut, cut_positions, cut_topology
from cutting._drill import DrillTopology, drill, drill_positions, drill_topology, refine
from cutting._geometry import MeshEdges, mesh_edges
from cutting._predicates import PREDICATES
from cutting._tear import TearTopology, scalpel_path, tear, tear_positions, tear_topology
from cutting._tools import Drill, Plane, Scalpel
from cutting._weights import blend_weights

__all__ = [
    "PREDICATES",
    "CutTopology",
    "Drill",
    "DrillTopology",
    "MeshEdges",
    "Plane",
    "Scalpel",
    "TearTopology",
    "blend_weights",
    "cut",
    "cut_positions",
    "cut_topology",
    "drill",
    "drill_positions",
    "drill_topology",
    "mesh_edges",
    "refine",
    "scalpel_path",
    "tear",
    "tear_positions",
    "tear_topology",
]
