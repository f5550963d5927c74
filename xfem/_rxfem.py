"""The RXFEM baseline: Koschier, Bender, Thuerey 2017, "Robust eXtended Finite Elements for Complex Cutting of
Deformables" (ACM TOG 36(4), SIGGRAPH 2017; [KBT17] in the XFEM paper), the method that Table 2 of the XFEM paper
compares against (its sec. 5.2). A comparison method on the same FEM core (``xfem._backward_euler``), not a
default.

What [KBT17] does (its abstract; the XFEM paper, sec. 2 and 5.2):

* Cuts are triangle-mesh surfaces; the displacement is enriched by Heaviside (sign) functions of the cut
  surfaces, ``u(X) = sum_i phi_i u_i + sum_c sum_i phi_i H^c(X) a_i^c``, for the nodes whose support a cut
  separates. Intersecting cuts are not supported (XFEM paper, sec. 1, 2 and 5.2: "their approach does not support
  the case of intersecting cuts").
* The integrals over the element subdomains are computed by specialized quadrature rules built per dissected
  element without representing the subdomains explicitly: moment fitting, points at fixed positions in the
  element and weights that integrate the subdomain's polynomial moments (computed by the divergence theorem over
  the cut surface clipped to the element and the element's faces). The elastic energy and its derivatives use a
  24-point rule per element subdomain in every time step (XFEM paper, sec. 5.2: the source of RXFEM's dPsi cost in
  Table 2).
* DOFs that do not contribute (an enriched basis function with no material under it) are constrained, and the
  linear solve is preconditioned with a preconditioner built from the quadrature weights.

What this module reproduces, and what it assumes:

* Enrichment. For cuts that do not intersect, a node whose support k cuts separate has k + 1 sides, and the
  Heaviside space ``u_i + sum_c H^c(side) a_i^c`` is the space of one copy ``u_i^s`` per side: the map from
  (u_i, a_i^c) to the copies is linear and invertible (H in {0, 1}). The FEM core takes one position per DOF, so
  the model keeps the copies (the DOFs of ``XFEMModel``: a nodal subdomain each). Backward Euler's minimizer does
  not depend on the basis, and neither does a Newton iteration: its direction is affine invariant, and the element
  Hessians are projected in F-space (``xfem._neohookean``), which a change of DOF basis does not touch. So the
  step is [KBT17]'s step in the copies' coordinates. Non-contributing DOFs: a nodal subdomain that no element
  piece reaches gets no DOF (``XFEMModel._renumber``), which is constraining its enrichment to zero.
* Intersecting cuts are refused: ``RXFEMModel.cut`` raises ValueError when the new cut solid overlaps an earlier
  one inside the body (``rxfem_schedule`` splits a scene's cuts into those RXFEM can make and the rest).
* Geometry. Which elements and node supports a cut separates, and the cut pieces' polynomial moments, come from
  the same closed cut solids (the open surface thickened by epsilon, ``cut_solid``) and the same manifold3d
  Booleans as ours (``xfem._subdomains``). [KBT17] computes those moments from the cut surface clipped to each
  element instead; the moments are the same exact integrals, so only the cost of that stage differs (the
  Booleans are reported separately, Table 2's MB column).
* Quadrature (moment fitting). Each piece of a cut element gets a 24-point rule: the positions of Keast's
  24-point degree-6 rule of its element (``KEAST24``, barycentric) and the minimum-norm weights that integrate
  the piece's moments up to degree 2 exactly (10 equations: the degree of the linear shape functions' mass
  products ``phi_a phi_b``). The piece's mass ``rho sum_q w_q phi_a(X_q) phi_b(X_q)`` (eq. 13), loads
  ``sum_q w_q phi_a(X_q)`` (eq. 14) and volume ``sum_q w_q`` are the rule's; they equal the exact integrals
  of ``XFEMModel`` to rounding. The degree fitted and the point positions are assumptions: [KBT17]'s exact choice
  is not in the sources available here.
* Elastic energy: 24 evaluations per piece of a cut element, every step. Each piece enters the core as 24 element
  rows with the piece's DOFs and shape gradients. F is constant on a piece (linear tets), so every row has the
  same energy density and the rule's value is ``psi(F) sum_q w_q = psi(F) |p|`` whatever the weights' split; the
  core takes non-negative weights (moment fitting gives weights of either sign), so the rows carry ``|p| / 24``
  each. The values are those of a single evaluation; the cost (24 energies, gradients and projected Hessians) is
  the rule's. The core also assembles each row on its own (24 scatters of a 12 x 12 block per piece, where an
  implementation that sums its points first scatters once), so RXFEM's dPsi here is an upper bound of the rule's
  cost by that assembly. Uncut elements keep the one-point rule of linear tets, as in [KBT17].
* Linear solver: the core's (CHOLMOD up to 1,000 unknowns, Jacobi-preconditioned CG above; ``xfem._backward_euler``).
  [KBT17]'s preconditioner, built from its quadrature weights, is not reproduced: Jacobi scaling is a diagonal
  scaling of the same system, and the CG column of Table 2 then times the core's solve of each method's system.
"""

from __future__ import annotations

import dataclasses

import manifold3d
import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int

from _jaxcga_shared.checks import check_real
from xfem._backward_euler import State, SystemCapacity
from xfem._capacity import _FLOOR, _GROWTH, _HEADROOM, Capacities, CompiledSteps, PaddedSystem
from xfem._cuts import cut_solid
from xfem._scenes import Scene, ScheduledCut
from xfem._subdomains import CutReport, MeshSolid, check_cut, solid_mesh
from xfem._tetmesh import TetMesh, boundary_faces
from xfem._xfem import CutDelta, XFEMModel, model_arguments

# Keast's 24-point rule of degree 6 on a tetrahedron: barycentric orbits and weights (fractions of the volume)
_ORBITS_4 = ((0.214602871259151684, 0.0399227502581679), (0.0406739585346113397, 0.0100772110553207),
             (0.322337890142275646, 0.0553571815436544))  # fmt: skip
_ORBIT_12 = (0.0636610018750175299, 0.269672331458315867, 0.603005664791649076, 27 / 560)


def _keast24() -> tuple[np.ndarray, np.ndarray]:
    points, weights = [], []
    for a, w in _ORBITS_4:
        for k in range(4):
            point = np.full(4, a)
            point[k] = 1 - 3 * a
            points.append(point)
            weights.append(w)
    a, b, c, w = _ORBIT_12
    for i in range(4):
        for j in range(4):
            if i != j:
                point = np.full(4, a)
                point[i], point[j] = b, c
                points.append(point)
                weights.append(w)
    return np.array(points), np.array(weights)


# one name per assignment, so that the documentation's static reader finds each constant and its docstring
_KEAST24_RULE = _keast24()
KEAST24 = _KEAST24_RULE[0]
"""(24, 4) barycentric points of Keast's degree-6 tetrahedron rule."""
KEAST24_WEIGHTS = _KEAST24_RULE[1]
"""(24,) weights of Keast's degree-6 tetrahedron rule, summing to 1."""

_POINTS = len(KEAST24)
_ROW_LEVELS = 64  # row levels per level of the other sizes (_RowCapacities): 1.5^64 rows, more than any model's
_OVERLAP = 1e-9  # a new cut overlapping an earlier one inside the body by more than this fraction: intersecting


def _degree2(y: np.ndarray) -> np.ndarray:
    """(..., 10) the monomials 1, y, y_i y_j (i <= j) of points y (..., 3)."""
    i, j = np.triu_indices(3)
    return np.concatenate([np.ones((*y.shape[:-1], 1)), y, y[..., i] * y[..., j]], axis=-1)


def moment_fitted_weights(
    Xe: Float[npt.ArrayLike, "P 4 3"],
    origin: Float[npt.ArrayLike, "P 3"],
    volume: Float[npt.ArrayLike, " P"],
    first: Float[npt.ArrayLike, "P 3"],
    second: Float[npt.ArrayLike, "P 3 3"],
) -> Float[np.ndarray, "P 24"]:
    """Moment fitting ([KBT17]): the minimum-norm weights of the 24 points ``KEAST24`` of each piece's element that
    integrate the piece's moments up to degree 2 exactly.

    Args:
        Xe: (P, 4, 3) the corners of each piece's tet.
        origin: (P, 3) the point the moments are taken about.
        volume: (P,) ``int_p 1``; first: (P, 3) ``int_p (X - o)``; second: (P, 3, 3) ``int_p (X - o)(X - o)^T``.
    Returns:
        (P, 24) weights w with ``sum_q w_q f(X_q) = int_p f`` for every polynomial f of degree <= 2 (to rounding).
    Raises:
        ValueError: shapes that differ from these, non-finite values, or a degenerate (flat) tet.
    """
    Xe = check_real("Xe", Xe, (None, 4, 3), "tet corners", rows="P")
    P = len(Xe)
    origin = check_real("origin", origin, (P, 3), "points")
    volume = check_real("volume", volume, (P,), "volumes")
    first = check_real("first", first, (P, 3), "first moments")
    second = check_real("second", second, (P, 3, 3), "second moments")
    edges = Xe[:, 1:] - Xe[:, :1]
    size = np.linalg.norm(edges, axis=2).max(axis=1, initial=0.0)
    if np.any(np.abs(np.linalg.det(edges)) <= 1e-12 * size**3):
        raise ValueError("Xe: a degenerate (flat) tet: its 24 points do not fit the 10 moments")
    # coordinates scaled by the tet's size: the 10 x 10 normal equations stay well conditioned
    scale = np.linalg.norm(Xe - origin[:, None], axis=2).max(axis=1)
    y = (np.einsum("qa,pad->pqd", KEAST24, Xe) - origin[:, None]) / scale[:, None, None]
    A = np.swapaxes(_degree2(y), 1, 2)  # (P, 10, 24)
    i, j = np.triu_indices(3)
    b = np.concatenate(
        [volume[:, None], first / scale[:, None], second[:, i, j] / (scale**2)[:, None]], axis=1
    )  # (P, 10)
    z = np.linalg.solve(A @ np.swapaxes(A, 1, 2), b[..., None])
    return (np.swapaxes(A, 1, 2) @ z)[..., 0]


class _RowCapacities(Capacities):
    """``XFEMModel``'s capacity levels with the element rows on a scale of their own: level ``k * _ROW_LEVELS + r``
    is level k of the nodes, mass entries and nonzeros, and level r of the rows. The 24 rows of each cut piece
    multiply the rows, not the DOFs: scaled together, the DOFs would be padded far beyond ours (and past the core's
    direct-solve size), a cost that is not RXFEM's."""

    def capacity(self, level: int) -> SystemCapacity:
        nodes_level, rows_level = divmod(level, _ROW_LEVELS)
        rows = max(_FLOOR[1], int(np.ceil(self.base[1] * _HEADROOM * _GROWTH**rows_level)))
        return super().capacity(nodes_level)._replace(elements=rows)


class RXFEMModel(XFEMModel):
    """A body cut by the RXFEM baseline ([KBT17], module docstring): ``XFEMModel``'s API (build with
    ``rxfem_model``, then ``cut`` and ``step``), with moment-fitted 24-point rules on the cut elements' pieces and
    no intersecting cuts.

    Attributes (besides ``XFEMModel``'s):
        rules: piece id -> (24,) its moment-fitted weights (pieces of cut elements).
        solids: the cut solids made so far, as applied (moved by their perturbations).
    """

    def __init__(
        self,
        mesh: TetMesh,
        rho: Float[np.ndarray, " m"],
        gravity: Float[np.ndarray, " 3"],
        fixed: Int[np.ndarray, " nb"],
        state: State,
        steps: CompiledSteps | None = None,
    ):
        self.rules: dict[int, np.ndarray] = {}
        self.solids: list[manifold3d.Manifold] = []
        self._body: manifold3d.Manifold | None = None
        super().__init__(mesh, rho, gravity, fixed, state, steps)
        nodes, rows, entries, nonzeros = self._capacities.base
        self._capacities = _RowCapacities((nodes, rows, entries, nonzeros))

    def body(self) -> manifold3d.Manifold:
        """The body's rest shape as a solid (its tets' boundary faces), for the intersection test."""
        if self._body is None:
            F = boundary_faces(self.T)
            mesh = manifold3d.Mesh64(
                vert_properties=np.array(self.X, np.float64, order="C"), tri_verts=np.array(F, np.uint64, order="C")
            )
            body = manifold3d.Manifold(mesh)
            if body.status() != manifold3d.Error.NoError or body.volume() <= 0:
                raise ValueError(f"mesh: its boundary faces are not a closed solid ({body.status().name})")
            self._body = body
        return self._body

    def intersecting(self, solid: manifold3d.Manifold) -> int | None:
        """The index (in ``solids``) of the first earlier cut that ``solid`` overlaps inside the body, or None."""
        if not self.solids:
            return None
        inside = solid ^ self.body()
        for k, earlier in enumerate(self.solids):
            overlap = (inside ^ earlier).volume()
            if overlap > _OVERLAP * min(inside.volume(), earlier.volume()):
                return k
        return None

    def cut(
        self,
        solid: manifold3d.Manifold | MeshSolid | tuple,
        perturb: float = 0.0,
        parallel: bool = True,
        epsilon: float | None = None,
    ) -> CutReport:
        """Cut the body (Algorithm 1 lines 1-25 of the XFEM paper on the cut's pieces, with [KBT17]'s moment-fitted
        rules on the touched elements).

        Args:
            solid: the closed cut solid (``cut_solid``, ``plane_cut_solid``) or its ``MeshSolid``, or a cut surface
                ``(V (n, 3), F (m, 3) int)``, an open oriented triangle mesh, thickened by ``epsilon``.
            perturb: 0, or the size of the gentle perturbation (``XFEMModel.cut``).
            parallel: run the Booleans on several threads.
            epsilon: the thickness of a cut surface (> 0); None for a solid.
        Returns:
            The ``CutReport``.
        Raises:
            ValueError: a bad solid or surface, or a cut that intersects an earlier one inside the body (RXFEM does
                not support intersecting cuts); the model is left unchanged.
        """
        if isinstance(solid, tuple) and not isinstance(solid, MeshSolid):
            if len(solid) != 2 or epsilon is None:
                raise ValueError("solid: a cut surface is a pair (V, F), thickened by a given epsilon > 0")
            solid = cut_solid(solid[0], np.asarray(solid[1]), epsilon)
        elif epsilon is not None:
            raise ValueError("epsilon: only for a cut surface (V, F); a solid has its own thickness")
        built = solid.build() if isinstance(solid, MeshSolid) else solid
        check_cut(built, perturb)
        earlier = self.intersecting(built)
        if earlier is not None:
            raise ValueError(
                f"solid: the cut intersects cut {earlier} inside the body; RXFEM (Koschier et al. 2017) does not "
                "support intersecting cuts (use xfem_model)"
            )
        report = super().cut(solid_mesh(built) if not isinstance(solid, MeshSolid) else solid, perturb, parallel)
        self.solids.append(built.transform(report.motion))
        return report

    def _integrate(self, elements: np.ndarray) -> int:
        """Moment fitting on every piece of the given elements: their 24-point rules, and mass, loads and volume by
        the rules (module docstring); returns the number of pieces."""
        measured = self._piece_moments(elements)
        if measured is None:
            return 0
        sids, owner, Xe, origin, moments, points = measured
        weights = moment_fitted_weights(Xe, origin, moments.volume, moments.first, moments.second)
        load = weights @ KEAST24  # (P, 4): sum_q w_q phi_a(X_q), phi_a(X_q) the points' barycentric coordinates
        mass = self.rho[owner][:, None, None] * np.einsum("pq,qa,qb->pab", weights, KEAST24, KEAST24)
        volume = weights.sum(axis=1)
        for k, sid in enumerate(sids):
            self._integrals[sid] = (float(volume[k]), mass[k], load[k], points[k])
            self.rules[sid] = weights[k]
        return len(sids)

    def _system_arrays(self):
        """``XFEMModel``'s system arrays with each piece of a cut element as 24 element rows (its quadrature points,
        weights ``|p| / 24``: module docstring)."""
        if self._arrays is None:
            dofs, grads, volume, M, force, fixed = super()._system_arrays()
            repeats = self.quadrature_rows()
            self._arrays = (
                np.repeat(dofs, repeats, axis=0),
                np.repeat(grads, repeats, axis=0),
                np.repeat(volume / repeats, repeats),
                M,
                force,
                fixed,
            )
        return self._arrays

    def quadrature_rows(self) -> Int[np.ndarray, " P"]:
        """(P,) int64 the element rows of each piece of ``piece_arrays`` in the system: 24 for a piece of a cut
        element, 1 for an uncut tet."""
        exact = np.fromiter(self._exact, np.int64, len(self._exact))
        return np.where(np.isin(self.piece_arrays()[0], exact), _POINTS, 1).astype(np.int64)

    def apply_delta(self, delta: CutDelta, padded: PaddedSystem | None = None) -> Int[np.ndarray, " n_dofs"]:
        """Not for RXFEM: a worker process's replica is an ``XFEMModel`` (exact integrals, no 24-point rows), so
        ``BackgroundCuts`` serves ``XFEMModel`` only.

        Raises:
            ValueError: always.
        """
        raise ValueError("model: cuts in a worker process (BackgroundCuts) are for XFEMModel only, not RXFEMModel")


def rxfem_model(
    mesh: TetMesh,
    density: float | Float[npt.ArrayLike, " m"],
    gravity: Float[npt.ArrayLike, " 3"] = (0.0, 0.0, -9.81),
    fixed: Int[npt.ArrayLike, " nb"] = (),
    state: State | None = None,
    steps: CompiledSteps | None = None,
) -> RXFEMModel:
    """An uncut body for the RXFEM baseline (Koschier et al. 2017; ``xfem._rxfem``): one DOF per node, one
    element row per tet, as ``xfem_model``.

    Args:
        mesh: the ``TetMesh``.
        density: scalar or (m,) positive mass density per tet.
        gravity: (3,) gravitational acceleration.
        fixed: (nb,) int mesh nodes held in place; () for none.
        state: the initial ``State`` over the n nodes (float64); None: at rest in the rest positions.
        steps: None, or a shared ``CompiledSteps`` (``xfem_model``).
    Returns:
        The ``RXFEMModel`` (close it when done, as an ``XFEMModel``).
    """
    return RXFEMModel(*model_arguments(mesh, density, gravity, fixed, state), steps=steps)


@dataclasses.dataclass(frozen=True)
class RXFEMScene(Scene):
    """A ``Scene`` whose ``model`` is an ``RXFEMModel`` (a scene run then runs the RXFEM baseline)."""

    def model(self, steps: CompiledSteps | None = None) -> RXFEMModel:
        """A fresh uncut ``RXFEMModel`` of the scene, at rest (``steps``: as ``Scene.model``)."""
        return rxfem_model(self.mesh, self.density, self.gravity, self.fixed, steps=steps)


def rxfem_schedule(scene: Scene) -> tuple[Scene, RXFEMScene, tuple[ScheduledCut, ...]]:
    """A scene's cuts split into those RXFEM can make, in order, and those that intersect an earlier one inside the
    body (tested at rest, before any perturbation).

    Args:
        scene: the ``Scene``.
    Returns:
        The scene with only the RXFEM cuts (for ``XFEMModel``: both methods then make the same cuts), the same as an
        ``RXFEMScene``, and the cuts left out.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene: expected a Scene (scene(name)), got {type(scene).__name__}")
    probe = rxfem_model(scene.mesh, scene.density, scene.gravity, scene.fixed)
    kept: list[ScheduledCut] = []
    left: list[ScheduledCut] = []
    for scheduled in sorted(scene.cuts, key=lambda c: c.frame):
        if probe.intersecting(scheduled.solid) is None:
            probe.solids.append(scheduled.solid)
            kept.append(scheduled)
        else:
            left.append(scheduled)
    ours = dataclasses.replace(scene, cuts=tuple(kept))
    fields = {f.name: getattr(ours, f.name) for f in dataclasses.fields(ours)}
    return ours, RXFEMScene(**fields), tuple(left)
