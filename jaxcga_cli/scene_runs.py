"""The runner of the XFEM paper's scenes (``xfem.scene``) with the timings of its Table 2, for ``jaxcga xfem``, the
benchmarks (``benchmarks/bench_xfem.py``) and the notebooks; not part of the library's API.

``run_scene`` applies each frame's cuts (``XFEMModel.cut``, Algorithm 1 lines 1-25), then one step (line 26), and
records per frame what Table 2 reports: Booleans and their time (MB), pieces integrated and their time (EI), the step
time; a cut frame's time is its cuts plus its step. Table 2's derivative (dPsi) and CG columns are inside the
jit-compiled step and not measured here (``benchmarks/bench_xfem.py`` times them on the final system). The step time
includes XLA compilation on the first frame of a process and when a cut moves the model to a capacity level whose
step is not compiled yet (``XFEMModel`` compiles the next level in the background, so this is rare once the run is
under way). With ``cut_latency=L`` the runner starts each cut in the background (``xfem.BackgroundCuts.submit``) in
its frame and makes it take effect L frames later: the frames between step while the cut is computed.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import jax
import manifold3d
import numpy as np

from xfem import BackgroundCuts, CompiledSteps, Scene, ScheduledCut, XFEMModel


@dataclass
class FrameRecord:
    """What one frame of ``run_scene`` did.

    Attributes:
        frame: the frame number (>= 1).
        cuts: cuts that took effect before the step.
        cut_seconds: wall time of the cut work on the frame's thread: ``XFEMModel.cut`` (Booleans, integration,
            enrichment) or, with a cut latency, starting cuts and committing them (waiting for them included).
        n_booleans, boolean_seconds: the Booleans of the cuts that took effect and their time.
        pieces_integrated, integration_seconds: element pieces integrated (eq. 21) and their time.
        step_seconds: wall time of the step (jit compilation included when it happened).
        dofs: 3 x the number of nodal DOFs after the frame's cuts.
        pieces: connected pieces of the body after the frame's cuts.
        cuts_started: cuts made in this frame (with a cut latency they take effect later).
        cutting: whether cut work was under way in this frame (a cut made, pending or taking effect).
    """

    frame: int
    cuts: int
    cut_seconds: float
    n_booleans: int
    boolean_seconds: float
    pieces_integrated: int
    integration_seconds: float
    step_seconds: float
    dofs: int
    pieces: int
    cuts_started: int = 0
    cutting: bool = False

    @property
    def seconds(self) -> float:
        """The frame's time: its cuts and its step."""
        return self.cut_seconds + self.step_seconds


@dataclass
class SceneRun:
    """The result of ``run_scene``.

    Attributes:
        scene: the ``Scene``.
        model: the ``XFEMModel`` in its final state.
        records: one ``FrameRecord`` per frame.
        applied: the cut solids as applied (moved by their perturbations), in order.
    """

    scene: Scene
    model: XFEMModel
    records: list[FrameRecord] = field(default_factory=list)
    applied: list[manifold3d.Manifold] = field(default_factory=list)

    def summary(self) -> dict[str, str | int | float]:
        """Table 2's figures as far as the runner measures them (times in seconds unless named ``_ms``):
        pieces and DOFs at the end, initial DOFs, Booleans and ms per Boolean (MB), pieces integrated and ms
        per piece (EI), step avg / max over all frames (a cut frame's time is its cuts plus its step), totals
        over cut frames (C) and all frames (C+U), and the uncut frames' average step."""
        records = self.records
        frame_s = np.array([r.seconds for r in records])
        cut = np.array([r.cuts > 0 for r in records])
        booleans = sum(r.n_booleans for r in records)
        integrated = sum(r.pieces_integrated for r in records)
        uncut_steps = [r.step_seconds for r in records if r.cuts == 0]
        return {
            "scene": self.scene.name,
            "size": self.scene.size,
            "frames": len(records),
            "cuts": sum(r.cuts for r in records),
            "nodes": int(self.scene.mesh.n_nodes),
            "elements": int(self.scene.mesh.n_elements),
            "pieces": records[-1].pieces if records else 1,
            "dofs_initial": 3 * int(self.scene.mesh.n_nodes),
            "dofs": records[-1].dofs if records else 3 * int(self.scene.mesh.n_nodes),
            "element_pieces": int(len(self.model.piece_arrays()[0])),
            "booleans": booleans,
            "boolean_ms": 1e3 * sum(r.boolean_seconds for r in records) / max(booleans, 1),
            "pieces_integrated": integrated,
            "integral_ms": 1e3 * sum(r.integration_seconds for r in records) / max(integrated, 1),
            "step_avg_s": float(frame_s.mean()) if len(records) else 0.0,
            "step_max_s": float(frame_s.max()) if len(records) else 0.0,
            "uncut_step_avg_s": float(np.mean(uncut_steps)) if uncut_steps else 0.0,
            "total_cut_frames_s": float(frame_s[cut].sum()),
            "total_s": float(frame_s.sum()),
        }


def run_scene(
    scene: Scene,
    steps: int | None = None,
    on_frame: Callable[[FrameRecord, XFEMModel], None] | None = None,
    cut_latency: int = 0,
    compiled_steps: CompiledSteps | None = None,
) -> SceneRun:
    """Simulate a scene: in each frame its scheduled cuts (Algorithm 1 lines 1-25), then one backward Euler step.

    Cut latency. With ``cut_latency = L > 0`` a cut scheduled for frame f is started in the background
    (``BackgroundCuts.submit``) before that frame's step and takes effect (``BackgroundCuts.commit``) before the
    step of frame f + L, waiting for it if needed: frames f to f + L - 1 step the body as it was, while the cut's
    Booleans, integrals and new system are computed beside them. The run does not depend on the threads' timing: it
    equals the run with latency 0 of the scene whose cuts are scheduled L frames later (to the rounding of manifold3d's
    parallel Booleans, which differs with the calling thread). L = 0: each cut is done in its frame.

    Args:
        scene: the ``Scene``.
        steps: frames to run (>= 1); None: ``scene.steps``. Cuts scheduled after the last frame are not applied;
            cuts started but not yet due at the end take effect after the last step.
        on_frame: None, or called after every frame with its ``FrameRecord`` and the model.
        cut_latency: L >= 0, in frames.
        compiled_steps: None (the run's model compiles its own steps), or a ``CompiledSteps`` shared by several
            runs of the scene (a benchmark's warm-up run compiles what the timed run steps).
    Returns:
        The ``SceneRun``; its model is the caller's to close (``run.model.close()``).
    Raises:
        ValueError: bad steps. RuntimeError: non-finite positions after a step.
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"scene: expected a Scene (scene(name)), got {type(scene).__name__}")
    steps = scene.steps if steps is None else steps
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    if not isinstance(cut_latency, int) or isinstance(cut_latency, bool) or cut_latency < 0:
        raise ValueError(f"cut_latency: expected an int >= 0 (frames), got {cut_latency!r}")
    model = scene.model(compiled_steps)
    run = SceneRun(scene, model)
    background = BackgroundCuts(model) if cut_latency else None
    if background is not None:  # its start (imports, the model's replica) is not a frame's work
        background.start()
    try:
        _run_frames(scene, model, run, steps, on_frame, cut_latency, background)
    finally:
        if background is not None:  # its worker process and thread end with the run
            background.close()
    return run


def _run_frames(
    scene: Scene,
    model: XFEMModel,
    run: SceneRun,
    steps: int,
    on_frame: Callable[[FrameRecord, XFEMModel], None] | None,
    cut_latency: int,
    background: BackgroundCuts | None,
) -> None:
    """``run_scene``'s frames, recorded into ``run``."""
    pieces = 1
    pending: list[tuple[int, ScheduledCut, object]] = []  # (frame it takes effect, the cut, its future)

    def took_effect(record: FrameRecord, scheduled: ScheduledCut, report) -> None:
        record.cuts += 1
        record.n_booleans += report.stats.n_booleans
        record.boolean_seconds += report.stats.boolean_seconds
        record.pieces_integrated += report.stats.pieces_integrated
        record.integration_seconds += report.stats.integration_seconds
        run.applied.append(scheduled.solid.transform(report.motion))

    def commit(record: FrameRecord, due: list) -> None:
        start = time.perf_counter()
        reports = background.commit(until=due[-1][2])  # pyright: ignore[reportOptionalMemberAccess]  # cuts pend only with a background
        record.cut_seconds += time.perf_counter() - start
        for (_, scheduled, _), report in zip(due, reports):
            took_effect(record, scheduled, report)

    for frame in range(1, steps + 1):
        record = FrameRecord(frame, 0, 0.0, 0, 0.0, 0, 0.0, 0.0, 0, pieces, cutting=bool(pending))
        due = [p for p in pending if p[0] <= frame]
        if due:
            pending = pending[len(due) :]
            commit(record, due)
        for scheduled in (c for c in scene.cuts if c.frame == frame):
            record.cuts_started += 1
            record.cutting = True
            start = time.perf_counter()
            if background is not None:  # cut_latency > 0
                pending.append((frame + cut_latency, scheduled, background.submit(scheduled.solid, scheduled.perturb)))
                record.cut_seconds += time.perf_counter() - start
            else:
                report = model.cut(scheduled.solid, scheduled.perturb)
                record.cut_seconds += time.perf_counter() - start
                took_effect(record, scheduled, report)
        if record.cuts:
            pieces = record.pieces = model.pieces()
        record.dofs = 3 * len(model.dof_sid)
        start = time.perf_counter()
        state = jax.block_until_ready(model.step(scene.h, scene.material, newton_iterations=scene.newton_iterations))
        record.step_seconds = time.perf_counter() - start
        if not np.all(np.isfinite(np.asarray(state.x))):  # numpy: a JAX check would compile per DOF count
            raise RuntimeError(f"{scene.name}: non-finite positions after frame {frame}")
        run.records.append(record)
        if on_frame is not None:
            on_frame(record, model)
    if pending:  # started, not yet due: they take effect after the last step
        commit(run.records[-1], pending)
        run.records[-1].pieces = model.pieces()
        run.records[-1].dofs = 3 * len(model.dof_sid)
