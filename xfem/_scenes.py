"""The five cutting scenes of the XFEM paper's results, sec. 5 (Ton-That, Kry, Andrews, "Generalized eXtended
Finite Element Method for Deformable Cutting via Boolean Operations"), with the parameters of sec. 5 and Table 1,
and the deformed surfaces of their pieces. (The runner that times them like Table 2 is the command line's:
``jaxcga xfem``.)

Parameters (sec. 5): stable neo-Hookean material, Young 1e6 (1e7 for the octopus),
Poisson 0.4, density 1e3, h = 0.033 s, one Newton iteration, gravity -9.81 along z. Table 1 gives the cut
thickness epsilon (1e-3 for the tetrahedron, 1e-4 otherwise) and the average edge length of each mesh, used here
as its scale (``average_edge`` is over the mesh's distinct edges). Every cut gets the gentle perturbation of
sec. 6.1 with a size of 1e-2 average edges (``apply_cut`` moves a cut only when a node lies within 1e-4 average
edges of its surface).

Scenes (``scene(name, size)``; size "paper" is Table 1's mesh and a cut every few frames, "small" a coarse mesh
with the cuts grouped into few frames, for tests and notebooks):

* ``sticks`` (Fig. 5, Table 1 "Cube"): the 5-tet unit cube (average edge 1.14) clamped at its x = 0 face, a
  cantilever, diced into 36 sticks along x by 5 vertical cuts (planes y = c) crossing 5 horizontal ones
  (z = c), alternating, one every 5 frames (small: the vertical ones in frame 1, the horizontal in frame 2).
* ``thin`` (Fig. 1): a 19 x 19 x 5 cell slab (2400 nodes, 7.2k DOFs; small 9 x 9 x 3), average edge 0.14,
  clamped at x = 0. Partial cuts parallel to its large faces from the free end to 35% of its length: the
  first halves its thickness, three more slice the bottom half into four thinner sheets, which sag more than the
  slab above and separate from it (sec. 5.1; below it, as there is no contact). The last cut, the plane x = 0.7 L
  across all the sheets (perpendicular to them and to their length, up to just inside the slab above), cuts off
  their outer parts: they lose mass and length and rise closer to rest (a cantilever's sag under its own weight
  grows as its length^4; a cut along them, halving their width, would leave it unchanged).
* ``cheese`` (Fig. 6, "Tetrahedron"): one tetrahedron (average edge 1.77, epsilon 1e-3) standing on its base
  (the three base nodes clamped), carved by two full wavy cuts (sinusoidal tool edges swept by translations),
  a partial wavy cut swept by a rotation, and two partial flat cuts, in different directions: many pieces and
  several subdomains per node in a single element.
* ``accordion`` (Fig. 7): a cube of 18 x 19 x 19 cells (7600 nodes, 22.8k DOFs; small 8 x 9 x 9), average edge
  0.17, hanging from its top face. Horizontal partial cuts every second cell layer (9 levels; small 4), from the
  x = 0 side to 80% of the width and from the other side to 20%, alternating: the body stays one piece, a
  zig-zag that stretches down. The last cut, the vertical plane x = 0.6 W between the two top levels, crosses
  both and releases everything below the top level's hinge: one piece becomes two.
* ``octopus`` (Fig. 8, "Octopus"): a real octopus, libigl's tutorial model octopus-low.mesh (Mark Pauly's;
  ``xfem/data``, licence in tests/data/README.md), head up, face along +x, scaled so that TetGen's mesh of its
  surface has Table 1's average edge (2.39: 6753 nodes, 20.3k DOFs, the paper's 20.8k; small about 3.0 and 7.8k
  DOFs; without TetGen, fTetWild at about the same average edge), Young 1e7, held at the back of its head and at
  its tentacles beyond the head's radius. A smiling wavy tool edge swept straight into its face carves the mouth;
  the second cut, a U-shaped edge whose sides cross the mouth, swept into the face less deep, frees the block under
  the mouth at its sides and floor: the jaw hangs from its back and drops.

``scene(name, size, last_cut=False)`` drops a scene's last cut, to compare the runs with and without it.

``piece_surfaces`` gives the deformed surfaces of the pieces (the mesh boundary and the cut faces, each piece's
triangles mapped by its own DOFs, eq. 18) for pictures and files.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import jax.numpy as jnp
import manifold3d
import numpy as np
from jaxtyping import Float, Int

import jaxcga as cga
from _jaxcga_shared.checks import check_choice
from _jaxcga_shared.mesh import TET_FACES
from _jaxcga_shared.tetmeshing import optional_tetgen
from xfem._capacity import CompiledSteps
from xfem._cuts import cut_solid, plane_cut_solid, sweep_between, swept_surface
from xfem._integration import linear_shape_coefficients
from xfem._material import Material
from xfem._surface_tets import tetrahedralize_surface
from xfem._tetmesh import (
    TetMesh,
    boundary_faces,
    box_tets,
    element_adjacency,
    five_tet_cube,
    one_tet,
    read_tet_mesh,
    tet_mesh,
    tetrahedralize,
)
from xfem._xfem import XFEMModel, xfem_model

SCENES = ("sticks", "thin", "cheese", "accordion", "octopus")
SIZES = ("paper", "small")

_PERTURB = 1e-2  # size of the gentle perturbation (sec. 6.1), in average edges
_ON_FACE = 1e-9  # a piece vertex with a barycentric coordinate below this lies on the opposite tet face


@dataclass(frozen=True)
class ScheduledCut:
    """A cut applied before the step of a frame.

    Attributes:
        frame: the frame (>= 1) whose step it precedes.
        solid: the closed cut solid (``cut_solid``, ``plane_cut_solid``).
        perturb: the gentle perturbation size (``XFEMModel.cut``).
        label: a short description.
    """

    frame: int
    solid: manifold3d.Manifold
    perturb: float
    label: str


@dataclass(frozen=True)
class Scene:
    """A cutting scene (host data: a mesh, its clamped nodes, material, time step and a schedule of cut solids;
    a plain dataclass because the manifold3d solids are not JAX data).

    Attributes:
        name: one of ``SCENES``.
        size: "paper" or "small".
        mesh: the ``TetMesh``.
        fixed: (nb,) int64 clamped nodes.
        young, poisson, density: material (Pa, 1, kg/m^3).
        h: time step (s).
        epsilon: cut thickness (Table 1).
        steps: default number of frames (the last cut is well before it).
        cuts: the ``ScheduledCut``s, by frame.
        newton_iterations: Newton iterations per step.
        gravity: (3,) gravitational acceleration.
    """

    name: str
    size: str
    mesh: TetMesh
    fixed: Int[np.ndarray, " nb"]
    young: float
    poisson: float
    density: float
    h: float
    epsilon: float
    steps: int
    cuts: tuple[ScheduledCut, ...]
    newton_iterations: int = 1
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.81)

    @property
    def material(self) -> Material:
        """The scene's ``Material`` (``young``, ``poisson``)."""
        return Material(self.young, self.poisson)

    @property
    def last_cut_frame(self) -> int:
        return max(c.frame for c in self.cuts)

    def model(self, steps: CompiledSteps | None = None) -> XFEMModel:
        """A fresh uncut ``XFEMModel`` of the scene, at rest (close it when done).

        Args:
            steps: None (the model compiles its own steps), or a ``CompiledSteps`` the scene's runs share (a
                second run then compiles nothing).
        """
        return xfem_model(self.mesh, self.density, self.gravity, self.fixed, steps=steps)


def average_edge(mesh: TetMesh) -> float:
    """The mean length of the mesh's distinct edges (Table 1's "average edge length")."""
    T = np.asarray(mesh.T)
    edges = np.stack([T[:, [0, 0, 0, 1, 1, 2]], T[:, [1, 2, 3, 2, 3, 3]]], axis=-1).reshape(-1, 2)
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    X = np.asarray(mesh.X)
    return float(np.linalg.norm(X[edges[:, 1]] - X[edges[:, 0]], axis=1).mean())


def _scaled(mesh: TetMesh, edge: float) -> TetMesh:
    """The mesh scaled about the origin so that its average edge is ``edge``."""
    return tet_mesh(np.asarray(mesh.X) * (edge / average_edge(mesh)), np.asarray(mesh.T))


def _rectangle(centre, u, w, half_u: float, half_w: float, epsilon: float) -> manifold3d.Manifold:
    """The flat cut ``centre + a u + b w``, |a| <= half_u, |b| <= half_w (u, w orthonormal), thickened by
    epsilon: the segment along u swept along w (``sweep_between``)."""
    centre, u, w = (np.asarray(v, np.float64) for v in (centre, u, w))
    edge = np.stack([centre - half_u * u - half_w * w, centre + half_u * u - half_w * w])
    V, F = sweep_between(jnp.asarray(edge), jnp.asarray(edge + 2 * half_w * w))
    return cut_solid(V, F, epsilon)


def _swept(edge, pivot, axis, angles, shifts, epsilon: float, samples: int = 6) -> manifold3d.Manifold:
    """The cut swept by a tool edge (p, 3) (world positions at the first key) through key poses: rotation by
    ``angles[k]`` about ``axis`` through ``pivot``, then translation by ``shifts[k]`` (``swept_surface``,
    logarithmic blending of the key motors)."""
    pivot = np.asarray(pivot, np.float64)
    angles = np.asarray(angles, np.float64)
    axes = np.broadcast_to(np.asarray(axis, np.float64), (len(angles), 3))
    motors = cga.motor(
        cga.rotor(jnp.asarray(axes), jnp.asarray(angles)), jnp.asarray(pivot + np.asarray(shifts, np.float64))
    )
    V, F = swept_surface(jnp.asarray(np.asarray(edge, np.float64) - pivot), motors, samples)
    return cut_solid(V, F, epsilon)


def _frames(size: str, paper: list[int], small: list[int]) -> list[int]:
    return paper if size == "paper" else small


def _sticks(size: str) -> Scene:
    mesh = five_tet_cube(1.0)
    epsilon = 1e-4
    perturb = _PERTURB * average_edge(mesh)
    # off-centre positions: no cut plane meets the cube's diagonals where they cross
    levels = np.arange(1, 6) / 6 + np.array([0.011, -0.007, 0.005, -0.013, 0.009])
    cuts, k = [], 0
    for i in range(5):
        for axis, name in ((1, "vertical y"), (2, "horizontal z")):
            point, normal = np.full(3, 0.5), np.eye(3)[axis]
            point[axis] = levels[i]
            frame = 5 * (k + 1) if size == "paper" else (1 if axis == 1 else 2)
            cuts.append(
                ScheduledCut(frame, plane_cut_solid(point, normal, 1.6, epsilon), perturb, f"{name} = {levels[i]:.3f}")
            )
            k += 1
    cuts.sort(key=lambda c: c.frame)
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 0] < 1e-9)
    return Scene("sticks", size, mesh, fixed, 1e6, 0.4, 1e3, 0.033, epsilon, 150 if size == "paper" else 3, tuple(cuts))


def _thin(size: str) -> Scene:
    cells = (19, 19, 5) if size == "paper" else (9, 9, 3)
    mesh = _scaled(box_tets(cells, size=cells), 0.14)
    epsilon = 1e-4
    L, W, T = np.asarray(mesh.X).max(axis=0)
    perturb = _PERTURB * 0.14
    margin = 0.1 * L
    start = 0.35 * L  # partial: the sheets stay attached to the slab's clamped part
    frames = _frames(size, [20, 40, 60, 80, 110], [1, 1, 1, 1, 2])
    cuts = []
    # the sheets hang below the slab (sec. 5.1: the thinner sheets sag more and separate from the thicker material
    # above; cut in the top half they would sag through it, there is no contact)
    for frame, level in zip(frames[:4], (0.5, 0.375, 0.25, 0.125)):
        x0, x1 = start, L + margin
        cuts.append(
            ScheduledCut(
                frame,
                _rectangle(
                    ((x0 + x1) / 2, W / 2, level * T), (1, 0, 0), (0, 1, 0), (x1 - x0) / 2, W / 2 + margin, epsilon
                ),
                perturb,
                f"sheet z = {level} T",
            )
        )
    # across all the sheets (the plane x = 0.7 L, perpendicular to them and to their length), up to just inside the
    # slab above them: their outer parts fall off, the sheets lose mass and length and rise (a cantilever's sag under
    # its own weight grows as its length^4; halving the width, as a cut along the sheets would, leaves it unchanged)
    z0, z1 = -margin, 0.55 * T
    cuts.append(
        ScheduledCut(
            frames[4],
            _rectangle(
                (0.7 * L + 0.013 * T, W / 2, (z0 + z1) / 2),
                (0, 1, 0),
                (0, 0, 1),
                W / 2 + margin,
                (z1 - z0) / 2,
                epsilon,
            ),
            perturb,
            "across the sheets x = 0.7 L",
        )
    )
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 0] < 1e-9 * L)
    return Scene("thin", size, mesh, fixed, 1e6, 0.4, 1e3, 0.033, epsilon, 200 if size == "paper" else 4, tuple(cuts))


def _wave(a, b, normal, amplitude: float, waves: float, points: int = 33) -> np.ndarray:
    """(points, 3) the polyline from a to b displaced by ``amplitude sin(2 pi waves t)`` along normal."""
    t = np.linspace(0.0, 1.0, points)[:, None]
    a, b, normal = (np.asarray(v, np.float64) for v in (a, b, normal))
    return (1 - t) * a + t * b + amplitude * np.sin(2 * np.pi * waves * t) * normal


def _cheese(size: str) -> Scene:
    mesh = _scaled(one_tet(), 1.77)
    s = float(np.asarray(mesh.X).max())  # the legs' length
    epsilon = 1e-3
    perturb = _PERTURB * 1.77
    m = 0.2 * s
    zero2 = np.zeros(2)
    frames = _frames(size, [10, 20, 30, 40, 50], [1, 1, 1, 2, 2])
    cuts = [
        # full wavy cuts: a sinusoidal edge along y swept along x (waves in z), one along x swept along z (in y)
        ScheduledCut(
            frames[0],
            _swept(
                _wave((-m, -m, 0.31 * s), (-m, s + m, 0.31 * s), (0, 0, 1), 0.05 * s, 2.5),
                (0, 0, 0),
                (0, 0, 1),
                zero2,
                [(0, 0, 0), (s + 2 * m, 0, 0)],
                epsilon,
            ),
            perturb,
            "wavy z ~ 0.31 s",
        ),
        ScheduledCut(
            frames[1],
            _swept(
                _wave((-m, 0.27 * s, -m), (s + m, 0.27 * s, -m), (0, 1, 0), 0.06 * s, 2.0),
                (0, 0, 0),
                (0, 0, 1),
                zero2,
                [(0, 0, 0), (0, 0, s + 2 * m)],
                epsilon,
            ),
            perturb,
            "wavy y ~ 0.27 s",
        ),
        # partial flat cuts
        ScheduledCut(
            frames[2],
            _rectangle((0.23 * s, 0.2 * s, 0.2 * s), (0, 1, 0), (0, 0, 1), 0.35 * s, 0.35 * s, epsilon),
            perturb,
            "flat x = 0.23 s, partial",
        ),
        ScheduledCut(
            frames[3],
            _rectangle(
                (0.3 * s, 0.3 * s, 0.12 * s),
                np.array([1, -1, 0]) / np.sqrt(2),
                np.array([1, 1, -1.5]) / np.sqrt(4.25),
                0.3 * s,
                0.25 * s,
                epsilon,
            ),
            perturb,
            "flat oblique, partial",
        ),
        # a wavy edge swept by a 70 degree rotation about the vertical axis through the apex: a partial fan
        ScheduledCut(
            frames[4],
            _swept(
                _wave((0.05 * s, 0.05 * s, 0.45 * s), (0.55 * s, 0.05 * s, 0.45 * s), (0, 0, 1), 0.03 * s, 1.5),
                (0.02 * s, 0.02 * s, 0.45 * s),
                (0, 0, 1),
                [0.0, np.radians(70)],
                np.zeros((2, 3)),
                epsilon,
            ),
            perturb,
            "wavy fan, partial",
        ),
    ]
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] < 1e-9 * s)
    return Scene("cheese", size, mesh, fixed, 1e6, 0.4, 1e3, 0.033, epsilon, 100 if size == "paper" else 3, tuple(cuts))


def _accordion(size: str) -> Scene:
    cells = (18, 19, 19) if size == "paper" else (8, 9, 9)
    mesh = _scaled(box_tets(cells, size=cells), 0.17)
    epsilon = 1e-4
    W, D, H = np.asarray(mesh.X).max(axis=0)
    perturb = _PERTURB * 0.17
    margin = 0.1 * W
    nz = cells[2]
    levels = [(j + 0.5) / nz * H for j in range(nz - 2, 0, -2)]  # mid-cell, every second layer, from the top
    every = 15
    cuts = []
    for k, z in enumerate(levels):
        x0, x1 = (-margin, 0.8 * W) if k % 2 == 0 else (0.2 * W, W + margin)
        frame = every * (k + 1) if size == "paper" else 1
        cuts.append(
            ScheduledCut(
                frame,
                _rectangle(((x0 + x1) / 2, D / 2, z), (1, 0, 0), (0, 1, 0), (x1 - x0) / 2, D / 2 + margin, epsilon),
                perturb,
                f"partial z = {z / H:.3f} H from x {'= 0' if k % 2 == 0 else '= W'}",
            )
        )
    # between the first two levels: the first one's span covers x < 0.8 W, the second one's x > 0.2 W
    cell = H / nz
    z0, z1 = levels[1] - 0.5 * cell, levels[0] + 0.5 * cell
    frame = cuts[-1].frame + (every if size == "paper" else 1)
    cuts.append(
        ScheduledCut(
            frame,
            _rectangle(
                (0.6 * W + 0.013 * cell, D / 2, (z0 + z1) / 2),
                (0, 1, 0),
                (0, 0, 1),
                D / 2 + margin,
                (z1 - z0) / 2,
                epsilon,
            ),
            perturb,
            "vertical x = 0.6 W: the release",
        )
    )
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] > H * (1 - 1e-9))
    return Scene(
        "accordion",
        size,
        mesh,
        fixed,
        1e6,
        0.4,
        1e3,
        0.033,
        epsilon,
        frame + 60 if size == "paper" else frame + 1,
        tuple(cuts),
    )


# the octopus (libigl's tutorial data, octopus-low.mesh: a tet mesh of Mark Pauly's model; licence in
# tests/data/README.md) in its own coordinates: its head's centre and axes, measured once (the head's tets'
# volume-weighted centroid and principal axis; the front is the azimuth with the least tentacle material near the
# head's lower half). Scaled by _OCTOPUS_SCALE its TetGen mesh at paper size has Table 1's average edge and DOFs.
_OCTOPUS_FILE = "octopus-low.mesh"
_OCTOPUS_CENTRE = (0.01398863, -0.0522888, -0.02998661)
_OCTOPUS_UP = (-0.0189, -0.3694, -0.9291)
_OCTOPUS_FRONT = (-0.9395, 0.3244, -0.1099)
_OCTOPUS_SCALE = 161.0


def octopus_mesh(size: str = "paper") -> TetMesh:
    """The ``octopus`` scene's tet mesh, in the scene's frame: the head's centre near the origin, +z up (out of the
    head's top), +x out of its face, scaled to Table 1's average edge (2.39) at paper size.

    Args:
        size: "paper": the model's surface (its tet mesh's boundary) tetrahedralized by TetGen (6753 nodes, average
            edge 2.39) or, without TetGen, by fTetWild at about the same average edge; "small": coarser (TetGen: 2592
            nodes, average edge 3.04).
    Returns:
        The ``TetMesh``.
    """
    check_choice("size", size, SIZES)
    coarse = read_tet_mesh(Path(__file__).parent / "data" / _OCTOPUS_FILE)
    up, front = np.asarray(_OCTOPUS_UP), np.asarray(_OCTOPUS_FRONT)
    up = up / np.linalg.norm(up)
    front = front - (front @ up) * up
    front = front / np.linalg.norm(front)
    R = np.stack([front, np.cross(up, front), up])
    X = (np.asarray(coarse.X) - np.asarray(_OCTOPUS_CENTRE)) @ R.T * _OCTOPUS_SCALE
    used, F = np.unique(boundary_faces(np.asarray(coarse.T)), return_inverse=True)  # the surface's vertices only
    X, F = X[used], F.reshape(-1, 3)
    if optional_tetgen() is not None:
        # TetGen's quality tets come out smaller than the regular tet of its volume bound: the bound of a regular
        # tet of edge 3 gives Table 1's octopus (average edge 2.39); the thin tentacles keep the small mesh's
        # edges near 3 even with a coarse bound (quality)
        edge = 3.0 if size == "paper" else 12.0
        return tetrahedralize(X, F, max_volume=edge**3 / (6 * np.sqrt(2)))
    # fTetWild's edges come out longer than its target, by 1/0.87
    target = 0.87 * (2.39 if size == "paper" else 3.04) / float(np.linalg.norm(np.ptp(X, axis=0)))
    return tetrahedralize_surface(X, F, edge_length=target).mesh


def _u_edge(x: float, half_width: float, z_top: float, z_bottom: float, arc_points: int = 7) -> np.ndarray:
    """(k, 3) a U-shaped tool edge in the plane at x: down the side y = -half_width from z_top, across at z_bottom,
    up the side y = +half_width, with rounded corners (radius a third of the half width)."""
    r = half_width / 3
    t = np.linspace(0.0, 0.5 * np.pi, arc_points)
    left = np.stack([-half_width + r - r * np.cos(t), z_bottom + r - r * np.sin(t)], axis=1)
    right = np.stack([half_width - r + r * np.sin(t), z_bottom + r - r * np.cos(t)], axis=1)
    yz = np.concatenate([[[-half_width, z_top]], left, right, [[half_width, z_top]]])
    return np.concatenate([np.full((len(yz), 1), x), yz], axis=1)


def _octopus(size: str) -> Scene:
    mesh = octopus_mesh(size)
    epsilon = 1e-4
    perturb = _PERTURB * average_edge(mesh)
    X = np.asarray(mesh.X)
    # the head: a ball of radius about 15 about (0, 0, 4), its face at x ~ 15; the tentacles leave its lower half
    z_mouth, outside = 9.0, 22.0
    # the mouth: a smiling edge (up at the corners, with a ripple: the paper's sinusoidal cut) swept straight into
    # the face, 17 deep (to x = -2)
    y = np.linspace(-10.0, 10.0, 33)
    smile = z_mouth + 2.5 * (y / 10.0) ** 2 + 0.6 * np.sin(3 * np.pi * y / 10.0)
    tool = np.stack([np.full_like(y, outside), y, smile], axis=1)
    mouth = _swept(tool, (0, 0, 0), (0, 0, 1), np.zeros(2), [(0, 0, 0), (-outside - 2.0, 0, 0)], epsilon)
    # the jaw: a U-shaped edge (two sides 14 apart crossing the mouth, a floor 7.5 below it) swept into the face to
    # x = 0, 2 less deep than the mouth: the block under the mouth keeps only its back, a hinge, and drops
    u = _u_edge(outside, 7.0, z_mouth + 3.5, z_mouth - 7.5)
    jaw = _swept(u, (0, 0, 0), (0, 0, 1), np.zeros(2), [(0, 0, 0), (-outside, 0, 0)], epsilon)
    frames = _frames(size, [20, 40], [1, 2])
    cuts = (
        ScheduledCut(frames[0], mouth, perturb, "the mouth: a smiling wavy edge swept into the face"),
        ScheduledCut(frames[1], jaw, perturb, "the jaw: a U-shaped edge crossing the mouth, swept less deep"),
    )
    # held at the back of its head and at its tentacles beyond the head's radius (free, the thin tentacles would
    # swing about and the whole body sag by metres under Young 1e7; the face and the jaw stay free)
    fixed = np.flatnonzero((np.linalg.norm(X[:, :2], axis=1) > 20.0) | (X[:, 0] < -10.0))
    return Scene("octopus", size, mesh, fixed, 1e7, 0.4, 1e3, 0.033, epsilon, 120 if size == "paper" else 3, cuts)


_BUILDERS = {"sticks": _sticks, "thin": _thin, "cheese": _cheese, "accordion": _accordion, "octopus": _octopus}


def scene(name: str, size: str = "paper", last_cut: bool = True) -> Scene:
    """Build one of the paper's scenes (module docstring).

    Args:
        name: one of ``SCENES``.
        size: "paper" (Table 1's meshes, a cut every few frames) or "small" (coarse meshes, the cuts grouped into
            the first few frames).
        last_cut: False drops the scene's last scheduled cut (the one each figure's claim is about: the thin
            sheets' cross cut, the accordion's release, the octopus's jaw), for comparing the runs with and without
            it; the frames to run stay the same.
    Returns:
        The ``Scene``.
    """
    if name not in _BUILDERS:
        raise ValueError(f"name: expected one of {SCENES}, got {name!r}")
    check_choice("size", size, SIZES)
    if not isinstance(last_cut, bool):
        raise ValueError(f"last_cut: expected a bool, got {last_cut!r}")
    built = _BUILDERS[name](size)
    return built if last_cut else dataclasses.replace(built, cuts=built.cuts[:-1])


def piece_surfaces(model: XFEMModel) -> tuple[Float[np.ndarray, "v 3"], Int[np.ndarray, "f 3"], Int[np.ndarray, " f"]]:
    """The deformed surfaces of the body's pieces: the mesh's boundary faces and the cut faces, each element
    piece's triangles mapped by its own DOFs (eq. 18: x(X) = sum_a phi_a(X) x_a^s on the piece).

    Uncut elements give their boundary faces; a cut element's piece gives the triangles of its solid except
    those on a tet face shared with a neighbour (interior).

    Args:
        model: the ``XFEMModel``.
    Returns:
        V (v, 3) deformed positions, F (f, 3) int64 triangles (each triangle has its own three vertices) and
        piece (f,) int64 the connected piece (``XFEMModel.components``) of each triangle.
    """
    element, dofs, _, _, _ = model.piece_arrays()
    _, label = model.components()
    x = np.asarray(model.state.x)
    X, T = model.X, model.T
    neighbour = element_adjacency(T)
    cut = np.array([model.sub.element_built(e) for e in range(len(T))], bool)  # pieces have solids
    # uncut elements: their outer faces, rest corners = the tet's nodes, mapped by the piece's DOFs
    uncut = np.flatnonzero(~cut[element])
    k, a = np.nonzero(neighbour[element[uncut]] < 0)
    corners = [x[dofs[uncut[k]][np.arange(len(k))[:, None], TET_FACES[a]]]]
    owner = [label[dofs[uncut[k], 0]]]
    # cut elements: each piece's solid, one pass over its sids in the order piece_arrays lists them
    for e in np.unique(element[cut[element]]).tolist():
        rows = np.flatnonzero(element == e)
        for row, sid in zip(rows.tolist(), model.sub.element_subdomains(e)):
            mesh = model.sub.element_solid(sid).to_mesh64()
            Vp = np.asarray(mesh.vert_properties, np.float64)[:, :3]
            Fp = np.asarray(mesh.tri_verts, np.int64)
            c, _ = linear_shape_coefficients(np.repeat(X[T[e]][None], len(Vp), axis=0), Vp)
            interior = np.zeros(len(Fp), bool)
            for face in range(4):
                if neighbour[e, face] >= 0:
                    interior |= np.all(np.abs(c[Fp, face]) < _ON_FACE, axis=1)
            Fp = Fp[~interior]
            corners.append((c @ x[dofs[row]])[Fp])
            owner.append(np.full(len(Fp), label[dofs[row, 0]]))
    V = np.concatenate(corners).reshape(-1, 3)
    return V, np.arange(len(V)).reshape(-1, 3), np.concatenate(owner).astype(np.int64)
