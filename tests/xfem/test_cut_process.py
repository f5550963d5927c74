"""Background cuts (``xfem._background``) and their worker process (``xfem._cut_process``, ``xfem._framing``): the
replica of a model, replayed from the cuts made before it started and kept in step through the deltas of
``XFEMModel`` and ``Subdomains``, gives the same model as cuts made in the model's own process; a dead or failing
worker raises at the commit and the next cut starts a new one; the worker ends with its ``BackgroundCuts``; the
protocol's framing; the requests sent ahead; the user's process keeps its affinities, priority, switch interval
and environment."""

import gc
import io
import os
import pickle
import sys
from typing import Any

import jax
import manifold3d
import numpy as np
import pytest

# the worker process, its framing and the mesh packing are internal to BackgroundCuts: tested here directly
import xfem._background
from _jaxcga_shared.host import to_devices
from tests.xfem._models import MATERIAL, RHO, G, H, plane, tall_box
from xfem import BackgroundCuts, xfem_model
from xfem._background import _ENTRY
from xfem._cut_process import CutProcess, CutProcessError
from xfem._framing import decode, encode, portable, read_frame, write_frame
from xfem._subdomains import MeshSolid, pack_meshes, solid_mesh, unpack_meshes

CUTS: list[dict[str, Any]] = [  # keyword arguments of plane()
    dict(point=(0.5, 0.5, 0.61), normal=(0.07, -0.04, 1.0)),
    dict(point=(0.5, 0.5, 0.9), normal=(0.03, 0.05, 1.0)),
    dict(point=(0.52, 0.5, 0.7), normal=(1.0, 0.04, 0.02)),
]


def _worker(background: BackgroundCuts) -> CutProcess:
    """The worker process of a started ``BackgroundCuts``."""
    assert background._process is not None, "the background cuts have no worker process"
    return background._process


def _models():
    mesh = tall_box()
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
    cut = plane()
    assert (rebuilt - cut).volume() == pytest.approx((solid - cut).volume(), rel=1e-14)
    meshes = [solid_mesh(solid), solid_mesh(cut), MeshSolid(np.zeros((0, 3)), np.zeros((0, 3), np.int64), 0.0)]
    for before, after in zip(meshes, unpack_meshes(pack_meshes(meshes))):
        np.testing.assert_array_equal(before.V, after.V)
        np.testing.assert_array_equal(before.F, after.F)
        assert before.tolerance == after.tolerance
    assert unpack_meshes(pack_meshes([])) == []


def test_subdomains_delta_makes_a_copy_equal():
    """``Subdomains.delta`` since a mark, applied to a copy as it was at the mark, makes it equal: the same ids,
    owners, parents, live lists and solids; a delta applied to subdomains that moved on is refused."""
    source, copy = _models()
    source.cut(plane(**CUTS[0]))
    copy.cut(plane(**CUTS[0]))
    mark = source.sub.mark()
    for cut in CUTS[1:]:
        source.cut(plane(**cut))
    delta = source.sub.delta(mark)
    copy.sub.apply_delta(delta)
    a, b = source.sub, copy.sub
    for kind in ("node", "element"):
        owners = range(a.n_nodes if kind == "node" else a.n_elements)
        live = [getattr(a, f"{kind}_subdomains")(o) for o in owners]
        assert live == [getattr(b, f"{kind}_subdomains")(o) for o in owners]
        for sid in (s for ids in live for s in ids):
            assert getattr(a, f"{kind}_parent")(sid) == getattr(b, f"{kind}_parent")(sid)
            assert getattr(b, f"{kind}_solid")(sid).volume() == pytest.approx(
                getattr(a, f"{kind}_solid")(sid).volume(), rel=1e-12
            )
    assert len(delta.elements.retired) > 0 and len(delta.elements.changed) > 0
    with pytest.raises(ValueError, match="delta"):
        copy.sub.apply_delta(delta)  # copy has the new ids already


@pytest.mark.slow
def test_replica_replays_earlier_cuts_and_direct_cuts():
    """Cuts made in the model's process before its worker started are replayed there, and so is a ``cut`` made
    directly while no cut is pending; the solids come back as meshes and are built on first use."""
    remote, inline = _models()
    for model in (remote, inline):
        model.cut(plane(**CUTS[0]))  # before any worker: in the model's process
    background = BackgroundCuts(remote)
    background.start()
    future = background.submit(plane(**CUTS[1]))
    inline.cut(plane(**CUTS[1]))
    assert background.commit(until=future)[0].dof_source is not None
    # which solids are still unbuilt meshes is internal to Subdomains (no public API): read directly
    received = [
        s
        for s in range(len(remote.sub._elements.owner))
        if remote.sub.element_alive(s) and isinstance(remote.sub._elements.solids[s], MeshSolid)
    ]
    assert received  # pieces made by the worker, not built yet
    for sid in received:
        assert remote.sub.element_solid(sid).volume() == pytest.approx(
            inline.sub.element_solid(sid).volume(), rel=1e-12
        )
    for model in (remote, inline):
        model.cut(plane(**CUTS[2]))  # directly, in the model's process
    outside = background.submit(plane(point=(0.5, 0.5, 5.0)))  # the replica replays CUTS[2] first
    assert background.commit()[0].dof_source is None  # outside the body: nothing changes
    assert outside.done() and len(remote.cuts) == 4
    _assert_same(remote, inline)
    background.close()


def test_the_worker_builds_its_systems_on_the_host_without_a_process_flag():
    """The worker's reply holds the padded system in numpy arrays (the parent puts it on its device), equal to the
    model's own padded system and level; built so by its arguments: this process's arrays still go to the device."""
    replica, model = _models()
    for m in (replica, model):
        m.cut(plane(**CUTS[0]))
    report, _, reply = xfem._background.replica_cut(
        replica, solid_mesh(plane(**CUTS[1])), 0.0, True, True, sent_system_bytes=1 << 40
    )
    assert reply is not None  # a delta's reply (delta=True) holds the system
    arrays, n, system, level = reply
    model.cut(plane(**CUTS[1]))
    padded = model.padded_system()
    assert system is not None and level == padded.level and n == len(model.dof_sid)
    leaves, expected = jax.tree.leaves(system), jax.tree.leaves(padded.system)
    assert all(type(leaf) is np.ndarray for leaf in leaves)
    assert all(isinstance(leaf, jax.Array) for leaf in expected)
    assert jax.tree.structure(system) == jax.tree.structure(padded.system)
    for got, want in zip(leaves, expected):
        np.testing.assert_array_equal(got, np.asarray(want))
    assert isinstance(to_devices(np.ones(2))[0], jax.Array)


@pytest.mark.slow
def test_cut_that_removes_material():
    """A cut that swallows the top layer of tets (and their nodes' subdomains, with their DOFs) and cuts into the
    next one: the same model through the worker."""
    remote, inline = _models()
    block = manifold3d.Manifold.cube((2.0, 2.0, 1.0)).translate((-0.5, -0.5, 0.93))
    for model in (remote, inline):
        model.step(H, MATERIAL)
    background = BackgroundCuts(remote)
    background.submit(block)
    inline.cut(block)
    report = background.commit()[0]
    assert any(not children for children in report.element_children.values())  # tets removed whole
    assert len(remote.dof_sid) < len(remote.X)
    _assert_same(remote, inline)
    background.close()


@pytest.mark.slow
def test_large_systems_are_padded_by_the_model(monkeypatch):
    """Above ``_SENT_SYSTEM_BYTES`` the worker sends the system arrays only, and the model pads them itself."""
    monkeypatch.setattr(xfem._background, "_SENT_SYSTEM_BYTES", 0)
    remote, inline = _models()
    sent = []
    prepare = remote.prepare_step
    monkeypatch.setattr(
        remote,
        "prepare_step",
        lambda arrays, n, system, level: (sent.append(system), prepare(arrays, n, system, level))[1],
    )
    background = BackgroundCuts(remote)
    for cut in CUTS:
        background.submit(plane(**cut))
        inline.cut(plane(**cut))
    background.commit()
    assert sent == [None] * len(CUTS)
    _assert_same(remote, inline)
    background.close()


@pytest.mark.slow
def test_dead_worker_raises_at_commit_and_the_next_cut_starts_a_new_one():
    remote, inline = _models()
    background = BackgroundCuts(remote)
    background.submit(plane(**CUTS[0]))
    background.commit()
    inline.cut(plane(**CUTS[0]))
    _worker(background).kill()  # fault injection: the worker dies
    failed, dropped = background.submit(plane(**CUTS[1])), background.submit(plane(**CUTS[2]))
    with pytest.raises(CutProcessError, match="exited"):
        background.commit()
    assert background.pending == 0
    assert dropped.cancelled() or isinstance(dropped.exception(), CutProcessError)
    assert failed.done()
    _assert_same(remote, inline)  # the failed cut changed nothing
    background.submit(plane(**CUTS[1]))  # a new worker, replaying the first cut
    inline.cut(plane(**CUTS[1]))
    background.commit()  # the new worker's cut matches the inline one
    _assert_same(remote, inline)
    background.close()


@pytest.mark.slow
def test_worker_errors_come_back_and_disagreement_is_caught():
    remote, inline = _models()
    background = BackgroundCuts(remote)
    background.start()
    with pytest.raises(TypeError):  # a malformed request: the worker's own error, raised here
        _worker(background).send(("not a cut",))
        _worker(background).receive()
    background._drop_process()
    background.submit(plane(**CUTS[0]))
    remote.cut(plane(**CUTS[1]))  # directly, while a cut is pending: the replica cannot know
    with pytest.raises(ValueError, match="delta"):  # checked before anything is applied
        background.commit()
    inline.cut(plane(**CUTS[1]))
    _assert_same(remote, inline)
    background.submit(plane(**CUTS[0]))  # a new worker, replaying the direct cut
    inline.cut(plane(**CUTS[0]))
    background.commit()
    _assert_same(remote, inline)
    background.close()
    error = portable(ValueError("perturb: bad"))
    assert isinstance(error, ValueError) and str(error) == "perturb: bad"

    class Local(Exception):  # defined in a function: it does not pickle
        pass

    error = portable(Local("x"))
    assert isinstance(error, RuntimeError) and "Local: x" in str(error)


@pytest.mark.slow
def test_worker_ends_with_its_background_cuts():
    remote, _ = _models()
    background = BackgroundCuts(remote)
    background.start()
    child = _worker(background)._child
    assert child.poll() is None
    del background
    gc.collect()
    assert child.wait(10) == 0


def test_worker_startup_failure_is_reported():
    process = CutProcess(
        dict(
            X=np.zeros((1, 3)),
            T=np.zeros((1, 4), np.int64),
            rho=np.ones(1),
            gravity=np.zeros(3),
            fixed=np.zeros(0, np.int64),
            log=[],
        ),
        _ENTRY,
    )
    try:
        with pytest.raises(ValueError, match="positive volume"):  # a flat tet: the replica's own check, raised here
            process.wait_ready()
    finally:
        process.close()


def test_messages_are_framed_whole():
    """Each message is its lengths, its pickle and its large arrays' buffers, read back whole, each buffer aligned to
    64 bytes (XLA's CPU client aliases such host arrays); a stream that ends early is an EOFError, not a hang."""
    large = np.arange(3000, dtype=np.float64).reshape(1000, 3)
    messages = [
        b"",
        ("one", np.arange(5)),
        {"system": (large, np.asfortranarray(large[:, :2]).astype(np.int32)), "small": np.ones(3)},
    ]
    stream = io.BytesIO()
    for message in messages:
        write_frame(stream, *encode(message))
    stream.seek(0)
    frames = [read_frame(stream) for _ in messages]
    assert [len(buffers) for _, buffers in frames] == [0, 0, 2]
    data, buffers = frames[2]
    assert len(data) < 1000  # the arrays travel out of band
    assert all(b.ctypes.data % 64 == 0 for b in buffers)
    back = [decode(data, buffers) for data, buffers in frames]
    assert back[0] == b"" and back[1][0] == "one"
    np.testing.assert_array_equal(back[1][1], np.arange(5))
    system = back[2]["system"]
    np.testing.assert_array_equal(system[0], large)
    np.testing.assert_array_equal(system[1], large[:, :2].astype(np.int32))
    assert system[1].flags.f_contiguous and system[0].ctypes.data % 64 == 0
    with pytest.raises(EOFError, match="the stream ended"):
        read_frame(stream)
    whole = io.BytesIO()
    write_frame(whole, *encode(messages[2]))
    for cut in (3, 40, len(whole.getvalue()) - 1):  # in the lengths, the pickle, the last buffer
        with pytest.raises(EOFError, match="within a message"):
            read_frame(io.BytesIO(whole.getvalue()[:cut]))
    assert pickle.loads(pickle.dumps(messages[1]))[0] == "one"


@pytest.mark.slow
def test_next_cut_is_sent_before_a_reply_is_prepared(monkeypatch):
    """The worker process starts the next pending cut as soon as it replies, while this process prepares the
    reply's system."""
    remote, inline = _models()
    background = BackgroundCuts(remote)
    background.start()
    events = []
    process, prepare = _worker(background), remote.prepare_step
    send = process.send
    monkeypatch.setattr(process, "send", lambda message: (events.append("send"), send(message))[1])
    monkeypatch.setattr(remote, "prepare_step", lambda *args: (events.append("prepare"), prepare(*args))[1])
    for cut in CUTS:  # queued while the worker makes the first one
        background.submit(plane(**cut))
    for cut in CUTS:
        inline.cut(plane(**cut))
    background.commit()
    assert events == ["send", "send", "prepare", "send", "prepare", "prepare"]
    _assert_same(remote, inline)
    background.close()


def _thread_affinities() -> dict[int, frozenset]:
    """The CPUs of each live thread of this process (a thread that ends while they are read is left out)."""
    affinities = {}
    for thread in os.listdir("/proc/self/task"):
        try:
            affinities[int(thread)] = frozenset(os.sched_getaffinity(int(thread)))
        except (ProcessLookupError, PermissionError):
            pass
    return affinities


@pytest.mark.skipif(
    not hasattr(os, "sched_getaffinity") or not os.path.isdir("/proc/self/task"), reason="needs Linux's CPU affinity"
)
@pytest.mark.slow
def test_background_cuts_leave_the_process_settings_alone():
    """A background cut changes nothing process-wide in the user's process: its CPU affinity and every thread's,
    its priority, the interpreter's switch interval and the environment stay as they were; the worker process
    runs with this process's priority and CPUs."""
    remote, inline = _models()
    before = (
        frozenset(os.sched_getaffinity(0)),
        _thread_affinities(),
        os.getpriority(os.PRIO_PROCESS, 0),
        sys.getswitchinterval(),
        dict(os.environ),
    )
    background = BackgroundCuts(remote)
    remote.step(H, MATERIAL)
    future = background.submit(plane(**CUTS[0]))
    while not future.done():  # steps while the cut is under way, as a simulation does
        remote.step(H, MATERIAL)
        assert frozenset(os.sched_getaffinity(0)) == before[0] and sys.getswitchinterval() == before[3]
    child = _worker(background).pid
    assert os.getpriority(os.PRIO_PROCESS, child) == before[2]
    assert os.sched_getaffinity(child) == before[0]
    background.commit()
    remote.step(H, MATERIAL)
    after = _thread_affinities()
    assert frozenset(os.sched_getaffinity(0)) == before[0]
    # the threads there before and still alive (an earlier test's compiling thread may end meanwhile)
    assert {t: a for t, a in after.items() if t in before[1]} == {t: a for t, a in before[1].items() if t in after}
    assert set(after.values()) <= {before[0]} | set(before[1].values())  # and those started since
    assert os.getpriority(os.PRIO_PROCESS, 0) == before[2]
    assert sys.getswitchinterval() == before[3]
    assert dict(os.environ) == before[4]
    background.close()
    inline.cut(plane(**CUTS[0]))
    np.testing.assert_array_equal(remote.dof_sid, inline.dof_sid)
