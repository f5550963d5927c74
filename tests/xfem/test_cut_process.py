"""The cut worker process (``xfem._cut_process``): its replica of a model, replayed from the cuts made before it
started, gives the same model as cuts made in the model's own process; a dead or failing worker raises at the
commit and the next cut starts a new one; the worker ends with its model; the protocol's framing, the requests
sent ahead, the turns with the steps, the worker's core and priority."""

import gc
import io
import os
import pickle
import sys
import threading

import manifold3d
import numpy as np
import pytest

import xfem._xfem
from tests.xfem.test_xfem import MATERIAL, RHO, G, H, _plane, _tall_box
from xfem._cut_process import (
    CutProcess,
    CutProcessError,
    _encode,
    _portable,
    _read_frame,
    _write_frame,
    pack_meshes,
    unpack_meshes,
)
from xfem._subdomains import MeshSolid, solid_mesh
from xfem._xfem import xfem_model

CUTS = [dict(point=(0.5, 0.5, 0.61), normal=(0.07, -0.04, 1.0)), dict(point=(0.5, 0.5, 0.9), normal=(0.03, 0.05, 1.0)),
        dict(point=(0.52, 0.5, 0.7), normal=(1.0, 0.04, 0.02))]


def _models():
    mesh = _tall_box()
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9)
    return [xfem_model(mesh, RHO, gravity=G, fixed=fixed) for _ in range(2)]


def _assert_same(a, b):
    assert a.pieces() == b.pieces()
    np.testing.assert_array_equal(a.dof_sid, b.dof_sid)
    np.testing.assert_array_equal(a.dof_node, b.dof_node)
    for x, y in zip(a.piece_arrays(), b.piece_arrays()):
        np.testing.assert_allclose(x, y, rtol=1e-12, atol=1e-15)
    for model in (a, b):
        model.step(H, MATERIAL)
    np.testing.assert_allclose(np.asarray(a.state.x), np.asarray(b.state.x), rtol=0, atol=1e-12)


def test_mesh_solid_round_trip():
    """A Manifold sent as its mesh: the same volume and Booleans; the packing keeps every mesh."""
    solid = manifold3d.Manifold.cube((1.0, 1.0, 1.0)) - manifold3d.Manifold.sphere(0.6, 24)
    rebuilt = solid_mesh(solid).build()
    assert rebuilt.volume() == pytest.approx(solid.volume(), rel=1e-14)
    cut = _plane()
    assert (rebuilt - cut).volume() == pytest.approx((solid - cut).volume(), rel=1e-14)
    meshes = [solid_mesh(solid), solid_mesh(cut), MeshSolid(np.zeros((0, 3)), np.zeros((0, 3), np.int64), 0.0)]
    for before, after in zip(meshes, unpack_meshes(pack_meshes(meshes))):
        np.testing.assert_array_equal(before.V, after.V)
        np.testing.assert_array_equal(before.F, after.F)
        assert before.tolerance == after.tolerance
    assert unpack_meshes(pack_meshes([])) == []


def test_replica_replays_earlier_cuts_and_takes_later_ones():
    """Cuts made in the model's process before its worker started are replayed there; ``cut`` after it started
    goes through the worker too; the solids come back as meshes and are built on first use."""
    remote, inline = _models()
    for model in (remote, inline):
        model.cut(_plane(**CUTS[0]))  # before any worker: in the model's process
    remote.start_cut_worker()
    assert remote._process is not None
    future = remote.cut_async(_plane(**CUTS[1]))
    inline.cut(_plane(**CUTS[1]))
    assert remote.commit_cuts(until=future)[0].staged
    remote.cut(_plane(**CUTS[2]))  # through the worker, in effect at once
    inline.cut(_plane(**CUTS[2]))
    assert not remote._pending
    _assert_same(remote, inline)
    received = [s for s in range(len(remote.sub._elements.owner)) if remote.sub.element_alive(s)
                and isinstance(remote.sub._elements.solids[s], MeshSolid)]
    assert received  # pieces made by the worker, not built yet
    for sid in received:
        assert remote.sub.element_solid(sid).volume() == pytest.approx(inline.sub.element_solid(sid).volume(),
                                                                      rel=1e-12)
    assert remote.cut(_plane(point=(0.5, 0.5, 5.0))).staged is False  # outside the body: nothing changes
    _assert_same(remote, inline)


def test_cut_that_removes_material():
    """A cut that swallows the top layer of tets (and their nodes' subdomains, with their DOFs) and cuts into the
    next one: the same model through the worker."""
    remote, inline = _models()
    block = manifold3d.Manifold.cube((2.0, 2.0, 1.0)).translate((-0.5, -0.5, 0.93))
    for model in (remote, inline):
        model.step(H, MATERIAL)
    remote.cut_async(block)
    inline.cut(block)
    report = remote.commit_cuts()[0]
    assert any(not children for children in report.element_children.values())  # tets removed whole
    assert len(remote.dof_sid) < len(remote.X)
    _assert_same(remote, inline)


def test_large_systems_are_built_by_the_model(monkeypatch):
    """Above ``_SENT_SYSTEM_BYTES`` the worker sends the system arrays only, and the model pads them itself."""
    monkeypatch.setattr(xfem._xfem, "_SENT_SYSTEM_BYTES", 0)
    remote, inline = _models()
    sent = []
    apply = remote._apply_remote
    remote._apply_remote = lambda report, delta: (sent.append(delta["system"]), apply(report, delta))[1]
    for cut in CUTS:
        remote.cut_async(_plane(**cut))
        inline.cut(_plane(**cut))
    remote.commit_cuts()
    assert sent == [None] * len(CUTS)
    _assert_same(remote, inline)


def test_dead_worker_raises_at_commit_and_the_next_cut_starts_a_new_one():
    remote, inline = _models()
    remote.cut_async(_plane(**CUTS[0]))
    remote.commit_cuts()
    inline.cut(_plane(**CUTS[0]))
    first = remote._process
    first._child.kill()
    first._child.wait()
    failed, dropped = remote.cut_async(_plane(**CUTS[1])), remote.cut_async(_plane(**CUTS[2]))
    with pytest.raises(CutProcessError, match="exited"):
        remote.commit_cuts()
    assert remote._process is None and not remote._pending and not remote._staged
    assert dropped.cancelled() or isinstance(dropped.exception(), CutProcessError)
    assert failed.done()
    _assert_same(remote, inline)  # the failed cut changed nothing
    remote.cut_async(_plane(**CUTS[1]))  # a new worker, replaying the first cut
    inline.cut(_plane(**CUTS[1]))
    remote.commit_cuts()
    assert remote._process is not first
    _assert_same(remote, inline)


def test_worker_errors_come_back_and_disagreement_is_caught():
    remote, _ = _models()
    remote.start_cut_worker()
    with pytest.raises(TypeError):  # a malformed request: the worker's own error, raised here
        remote._process.send(("not a cut",))
        remote._process.receive()
    remote._drop_process()
    with pytest.raises(CutProcessError, match="replica has"):  # checked before anything is applied
        remote._apply_remote(None, dict(counts=(0, 0)))
    error = _portable(ValueError("perturb: bad"))
    assert isinstance(error, ValueError) and str(error) == "perturb: bad"

    class Local(Exception):  # defined in a function: it does not pickle
        pass

    error = _portable(Local("x"))
    assert isinstance(error, RuntimeError) and "Local: x" in str(error)


def test_worker_ends_with_its_model():
    remote, _ = _models()
    remote.start_cut_worker()
    child = remote._process._child
    assert child.poll() is None
    del remote
    gc.collect()
    assert child.wait(10) == 0


def test_worker_startup_failure_is_reported():
    process = CutProcess(dict(x64=True, X=np.zeros((1, 3)), T=np.zeros((1, 4), np.int64), rho=np.ones(1),
                              gravity=np.zeros(3), fixed=np.zeros(0, np.int64), log=[]))
    try:
        with pytest.raises(ValueError, match="positive volume"):  # a flat tet: the replica's own check, raised here
            process.wait_ready()
    finally:
        process.close()


def test_messages_are_framed_whole():
    """Each message is its lengths, its pickle and its large arrays' buffers, read back whole, each buffer aligned to
    64 bytes (XLA's CPU client aliases such host arrays); a stream that ends early is an EOFError, not a hang."""
    large = np.arange(3000, dtype=np.float64).reshape(1000, 3)
    messages = [b"", ("one", np.arange(5)), {"system": (large, np.asfortranarray(large[:, :2]).astype(np.int32)),
                                            "small": np.ones(3)}]
    stream = io.BytesIO()
    for message in messages:
        _write_frame(stream, *_encode(message))
    stream.seek(0)
    frames = [_read_frame(stream) for _ in messages]
    assert [len(buffers) for _, buffers in frames] == [0, 0, 2]
    data, buffers = frames[2]
    assert len(data) < 1000  # the arrays travel out of band
    assert all(b.ctypes.data % 64 == 0 for b in buffers)
    back = [pickle.loads(data, buffers=buffers) for data, buffers in frames]
    assert back[0] == b"" and back[1][0] == "one"
    np.testing.assert_array_equal(back[1][1], np.arange(5))
    system = back[2]["system"]
    np.testing.assert_array_equal(system[0], large)
    np.testing.assert_array_equal(system[1], large[:, :2].astype(np.int32))
    assert system[1].flags.f_contiguous and system[0].ctypes.data % 64 == 0
    with pytest.raises(EOFError, match="the stream ended"):
        _read_frame(stream)
    whole = io.BytesIO()
    _write_frame(whole, *_encode(messages[2]))
    for cut in (3, 40, len(whole.getvalue()) - 1):  # in the lengths, the pickle, the last buffer
        with pytest.raises(EOFError, match="within a message"):
            _read_frame(io.BytesIO(whole.getvalue()[:cut]))


def test_next_cut_is_sent_before_a_reply_is_applied():
    """The worker process starts the next pending cut as soon as it replies, while the model applies the reply."""
    remote, inline = _models()
    remote.start_cut_worker()
    events = []
    process, apply = remote._process, remote._apply_remote
    send = process.send
    process.send = lambda message, turn=None: (events.append("send"), send(message, turn))[1]
    remote._apply_remote = lambda report, delta: (events.append("apply"), apply(report, delta))[1]
    with remote._turns.step():  # the worker cannot pickle the first request yet: all three are queued
        for cut in CUTS:
            remote.cut_async(_plane(**cut))
    for cut in CUTS:
        inline.cut(_plane(**cut))
    remote.commit_cuts()
    assert events == ["send", "send", "apply", "send", "apply", "apply"]
    _assert_same(remote, inline)


def test_steps_and_worker_pieces_take_turns(monkeypatch):
    """A step waits while a piece of the worker thread's work holds the turn; after a piece, the next one waits for
    a step to end, unless the model's thread waits for the worker (``hurry``) or nobody steps (``_PATIENCE``)."""
    monkeypatch.setattr(xfem._xfem, "_PATIENCE", 30.0)
    model, _ = _models()
    model.step(H, MATERIAL)  # compiled
    turns = model._turns
    turns.paced = True  # as for a model with short steps (``_SHORT_STEP_S``)
    done = threading.Event()
    with turns.piece():
        stepping = threading.Thread(target=lambda: (model.step(H, MATERIAL), done.set()))
        stepping.start()
        assert not done.wait(0.3)
    stepping.join(30)
    assert done.is_set()

    def next_piece(started):
        with turns.piece():
            started.set()

    with turns.piece():
        pass
    started = threading.Event()
    waiting = threading.Thread(target=next_piece, args=(started,))
    waiting.start()
    assert not started.wait(0.3)  # no step since the last piece
    model.step(H, MATERIAL)
    assert started.wait(10)
    waiting.join()
    started = threading.Event()
    waiting = threading.Thread(target=next_piece, args=(started,))
    waiting.start()
    assert not started.wait(0.3)
    with turns.hurry():
        assert started.wait(10)
    waiting.join()
    monkeypatch.setattr(xfem._xfem, "_PATIENCE", 0.05)
    started = threading.Event()
    waiting = threading.Thread(target=next_piece, args=(started,))
    waiting.start()
    assert started.wait(10)  # nobody steps: it goes after its patience
    waiting.join()


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="CPU affinity is Linux's")
def test_worker_runs_on_one_core_at_low_priority():
    """Background cuts run on one core at nice 19; a ``cut`` (the model waits for it) on all the parent's cores."""
    remote, _ = _models()
    remote.cut_async(_plane(**CUTS[0]))
    remote.commit_cuts()
    child = remote._process._child.pid
    cores = os.sched_getaffinity(0)
    assert os.sched_getaffinity(child) == {max(cores)}
    assert os.getpriority(os.PRIO_PROCESS, child) == 19
    remote.cut(_plane(**CUTS[1]))
    assert os.sched_getaffinity(child) == cores
    remote.cut_async(_plane(**CUTS[2]))
    remote.commit_cuts()
    assert os.sched_getaffinity(child) == {max(cores)}


def _thread_affinities() -> list[frozenset]:
    """The CPUs of each live thread of this process (a thread that ends while they are read is left out)."""
    affinities = []
    for thread in os.listdir("/proc/self/task"):
        try:
            affinities.append(frozenset(os.sched_getaffinity(int(thread))))
        except ProcessLookupError:
            pass
    return affinities


@pytest.mark.skipif(not hasattr(os, "sched_getaffinity") or len(os.sched_getaffinity(0)) < 2,
                    reason="needs Linux's CPU affinity and two cores")
def test_short_steps_keep_the_process_off_the_worker_core():
    """While a model with short steps has background cuts pending, every thread of the process stays off the
    worker's core (and its worker pieces are paced); afterwards each gets its CPUs back. Long steps keep all."""
    cores = os.sched_getaffinity(0)
    worker = max(cores)

    def affinities():
        return {frozenset(a) == cores - {worker} for a in _thread_affinities()}

    remote, _ = _models()
    remote.start_cut_worker()
    assert os.sched_getaffinity(remote._process._child.pid) == {worker}
    remote._last_step_seconds = 0.002  # as measured by its steps
    with remote._turns.step():  # the cut stays pending
        remote.cut_async(_plane(**CUTS[0]))
        assert affinities() == {True} and remote._turns.paced
    remote.commit_cuts()
    assert os.sched_getaffinity(0) == cores and affinities() == {False}
    remote._last_step_seconds = 1.0
    with remote._turns.step():
        remote.cut_async(_plane(**CUTS[1]))
        assert os.sched_getaffinity(0) == cores and not remote._turns.paced
    remote.commit_cuts()
    assert os.sched_getaffinity(0) == cores


def test_a_model_dropped_with_pending_cuts_gives_back_the_process_settings():
    """The switch interval and the reservation of the worker's core end with the model, even with cuts pending."""
    interval = sys.getswitchinterval()
    remote, _ = _models()
    remote.start_cut_worker()
    remote._last_step_seconds = 0.002
    future = remote.cut_async(_plane(**CUTS[0]))
    assert sys.getswitchinterval() < interval
    future.result()
    del remote, future
    gc.collect()
    assert sys.getswitchinterval() == interval
    if hasattr(os, "sched_getaffinity"):
        cores = os.sched_getaffinity(0)
        assert set(_thread_affinities()) == {frozenset(cores)}
