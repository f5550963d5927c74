"""xfem: tetrahedral FEM, the generalized XFEM of the XFEM paper and physics on rigged characters, on the jaxcga
kernel.

Sec. 3 of the paper, the simulation core: ``_tetmesh`` (tet meshes: generators, TetGen, meshio files,
boundary faces, one-rings, adjacency), ``_surface_tets`` (fTetWild's tets of any surface, the surface embedded in
them, the tets' quality), ``_linear_tet`` (linear shape functions eq. 5, consistent and
lumped mass eq. 7, body forces eq. 8), ``_neohookean`` (stable neo-Hookean energy, stress and
PSD-projected Hessians; ``_jacobi3``, the batched 3 x 3 SVD and eigendecomposition of their eigensystem),
``_assembly`` (sparse patterns precomputed on the host, assembly in JAX),
``_backward_euler`` (eq. 10 as a minimization: projected Newton with line search, to convergence or the paper's
one iteration, ``SolveStats``, Dirichlet nodes, implicit gradients), ``_material`` (``Material``: Young's
modulus and Poisson's ratio), ``_rollout`` (steps in
a checkpointed ``lax.scan``, differentiable in the initial state, material, forces and moving targets). The
step is generic over an element list (DOF-node indices, shape gradients, integration weights) and any mass
matrix, so the enriched XFEM elements go through the same code.

Sec. 4, the generalized XFEM: ``_cuts`` (swept tool edges thickened into closed solids, sec. 4.1), ``_subdomains``
(nodal and element subdomains cut by manifold3d Booleans, Algorithm 1 lines 1-19), ``_integration`` (exact
divergence-theorem moments of the pieces, eq. 13, 14, 21), ``_xfem`` (``XFEMModel``: indicator enrichments eq.
16-18, DOF duplication, pieces on the FEM core), ``_capacity`` (systems padded to capacity levels so that cuts reuse
the compiled step), ``_background`` (``BackgroundCuts``: cuts computed in a worker process, ``_cut_process`` and
``_framing``, while the model steps), ``_material`` (``Material``), ``_rollout`` (``rollout``: a differentiable
``lax.scan`` of steps), ``_simulate`` (trajectories across a schedule of cuts, differentiable through the cuts' DOF
copy maps and in the planes of plane cuts; ``plan_cuts``, the host phase as a ``CutPlan`` the caller holds and
passes; ``plane_cut_simulation`` for jit and vmap over the planes), ``_cut_system`` (slab cuts whose placement is a
differentiable parameter). Sec. 5: ``_scenes`` (the paper's five scenes with Table 1's parameters, a runner timing
them like Table 2; ``jaxcga xfem SCENE`` runs them), ``_rxfem`` (the RXFEM baseline of Koschier et al. 2017 that
Table 2 compares against, on the same core: Heaviside enrichment without intersecting cuts, moment-fitted 24-point
rules on the cut elements' pieces).
"""

from xfem._assembly import AssemblyPattern, CapacityError, assemble_matrix, assemble_vector, assembly_pattern
from xfem._background import BackgroundCuts
from xfem._backward_euler import (
    FEMSystem,
    SolveStats,
    State,
    SystemCapacity,
    backward_euler_step,
    fem_from_mesh,
    fem_system,
    mechanical_energy,
)
from xfem._capacity import CompiledSteps
from xfem._character import CharacterMotion, CharacterSegment, simulate_character
from xfem._character_body import CharacterBody, character_body, transfer_weights
from xfem._character_reduced import CharacterSubspace, character_subspace
from xfem._cut_system import PlaneCuts, cut_system, plane_cuts
from xfem._cuts import blade_solid, cut_solid, plane_cut_solid, sweep_between, swept_surface, thicken
from xfem._integration import Moments, element_piece_integrals, moments_of_pieces, polyhedron_moments
from xfem._linear_tet import body_force, consistent_mass, lumped_mass, shape_functions, shape_gradients
from xfem._material import Material
from xfem._neohookean import (
    element_energy,
    element_gradient_hessian,
    lame,
    stable_neohookean_energy,
    stable_neohookean_pk1,
)
from xfem._rollout import rollout
from xfem._rxfem import (
    KEAST24,
    KEAST24_WEIGHTS,
    RXFEMModel,
    RXFEMScene,
    moment_fitted_weights,
    rxfem_model,
    rxfem_schedule,
)
from xfem._scenes import SCENES, SIZES, Scene, ScheduledCut, piece_surfaces, scene
from xfem._simulate import CutPlan, PlaneCutSimulation, plan_cuts, plane_cut_simulation, simulate
from xfem._subdomains import CutReport, CutStats, Subdomains, apply_cut, subdomains
from xfem._surface_tets import (
    SurfaceEmbedding,
    SurfaceTets,
    TetQuality,
    cut_surface,
    embed_points,
    surface_map,
    tet_quality,
    tetrahedralize_surface,
)
from xfem._tetmesh import (
    TetMesh,
    boundary_faces,
    box_tets,
    element_adjacency,
    five_tet_cube,
    node_rings,
    one_tet,
    read_tet_mesh,
    tet_mesh,
    tet_volumes,
    tetrahedralize,
)
from xfem._xfem import XFEMModel, xfem_model

__all__ = [
    "CompiledSteps",
    "CharacterBody",
    "CharacterMotion",
    "CharacterSegment",
    "character_body",
    "simulate_character",
    "transfer_weights",
    "surface_map",
    "CharacterSubspace",
    "character_subspace",
    "SCENES",
    "SIZES",
    "ScheduledCut",
    "Scene",
    "piece_surfaces",
    "scene",
    "PlaneCuts",
    "cut_system",
    "plane_cuts",
    "blade_solid",
    "cut_solid",
    "plane_cut_solid",
    "sweep_between",
    "swept_surface",
    "thicken",
    "Moments",
    "element_piece_integrals",
    "moments_of_pieces",
    "polyhedron_moments",
    "BackgroundCuts",
    "CutReport",
    "CutStats",
    "Subdomains",
    "apply_cut",
    "subdomains",
    "XFEMModel",
    "KEAST24",
    "KEAST24_WEIGHTS",
    "RXFEMModel",
    "RXFEMScene",
    "moment_fitted_weights",
    "rxfem_model",
    "rxfem_schedule",
    "CutPlan",
    "PlaneCutSimulation",
    "plan_cuts",
    "plane_cut_simulation",
    "simulate",
    "xfem_model",
    "AssemblyPattern",
    "CapacityError",
    "SystemCapacity",
    "FEMSystem",
    "Material",
    "SolveStats",
    "State",
    "TetMesh",
    "assemble_matrix",
    "assemble_vector",
    "assembly_pattern",
    "backward_euler_step",
    "body_force",
    "boundary_faces",
    "box_tets",
    "consistent_mass",
    "element_adjacency",
    "element_energy",
    "element_gradient_hessian",
    "fem_from_mesh",
    "fem_system",
    "five_tet_cube",
    "lame",
    "lumped_mass",
    "mechanical_energy",
    "node_rings",
    "one_tet",
    "read_tet_mesh",
    "rollout",
    "shape_functions",
    "shape_gradients",
    "stable_neohookean_energy",
    "stable_neohookean_pk1",
    "tet_mesh",
    "tet_volumes",
    "tetrahedralize",
    "SurfaceEmbedding",
    "SurfaceTets",
    "TetQuality",
    "cut_surface",
    "embed_points",
    "tet_quality",
    "tetrahedralize_surface",
]
