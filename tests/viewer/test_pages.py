"""The viewer's pages in a real browser (headless Chromium, ``browser`` in conftest.py): each kind of page is
loaded, its state (``window.jaxcgaViewer``) is what Python wrote, the vertices it draws at a time are those of
``deform.skin_model`` (a glTF played by three.js's loader and mixer, an implementation of glTF independent of
deform's) or of the frames written, to 1e-4 of the bounding-box diagonal, and a screenshot is not blank. A page
whose data is corrupted shows the error on the page and in its state."""

from __future__ import annotations

import re
import time
from collections.abc import Callable
from pathlib import Path

import jax
import meshio
import numpy as np
import pytest
import trimesh

import deform
from _jaxcga_shared.mesh import bounding_diagonal
from tests.shared import tube

DATA = Path(__file__).resolve().parents[1] / "data"
BACKGROUND = np.array([242, 242, 240])  # the page's background colour, 0xf2f2f0


def _show(browser, page: deform.View, folder: Path, name: str = "view.html") -> dict:
    """Save ``page``, load it, and return its state once ready, with no error."""
    path = page.save(folder / name)
    state = browser.open(path)
    assert state["errors"] == [] and state["ready"], state["errors"]
    return state


def _drawn_fraction(browser) -> float:
    """Fraction of the drawing area's pixels (above the control bar) that differ from the background."""
    image = browser.screenshot()[:-80].astype(int)
    return float((np.abs(image - BACKGROUND).max(axis=-1) > 12).mean())


def _compare_counts(state: dict, page: deform.View) -> None:
    """The page's meshes are those Python read and wrote (counts from three.js's geometry against Python's)."""
    shown = [{k: m[k] for k in ("name", "kind", "vertexCount", "triangleCount", "source")} for m in state["meshes"]]
    assert shown == list(page.meshes)


@pytest.mark.parametrize("name", ["CesiumMan", "RiggedSimple"])
def test_a_skinned_gltf_plays_as_deform_skins_it(browser, tmp_path, name):
    path = DATA / f"{name}.glb"
    page = deform.view(path)
    state = _show(browser, page, tmp_path)
    model = deform.load_model(path)
    _compare_counts(state, page)
    assert state["meshes"][0]["kind"] == "skinned"
    assert state["meshes"][0]["vertexCount"] == model.mesh.num_vertices
    assert state["meshes"][0]["triangleCount"] == len(model.mesh.F)
    duration = float(model.clip(0).end)
    assert [c["name"] for c in state["clips"]] == [c["name"] for c in page.clips]
    assert state["clips"][0]["duration"] == pytest.approx(duration, rel=1e-6)
    assert state["duration"] == pytest.approx(duration, rel=1e-6) and state["playing"]
    assert state["renderer"] and state["antialias"] == ("SwiftShader" not in state["renderer"])

    skin = jax.jit(lambda t: deform.skin_model(model, t, method="lbs"))
    diag = bounding_diagonal(model.mesh.V)
    shown = {}
    for t in (0.0, 0.31 * duration, 0.77 * duration, duration):
        shown[t] = browser.positions(0, t)
        np.testing.assert_allclose(shown[t], np.asarray(skin(t)), rtol=0, atol=1e-4 * diag)
    assert np.abs(shown[0.31 * duration] - shown[0.0]).max() > 0.02 * diag  # the clip moves the mesh
    assert browser.state()["time"] == pytest.approx(duration)
    assert _drawn_fraction(browser) > 0.01


def test_a_gltf_with_its_bin_is_embedded(browser, tmp_path):
    """A .gltf with an external .bin (as ``deform.save_model`` writes it) is embedded whole: the page needs no
    file beside it."""
    model = deform.load_model(DATA / "RiggedSimple.glb")
    deform.save_model(model, tmp_path / "simple.gltf")
    page = deform.view(tmp_path / "simple.gltf")
    (tmp_path / "simple.bin").unlink()
    state = _show(browser, page, tmp_path)
    _compare_counts(state, page)
    skin = jax.jit(lambda t: deform.skin_model(model, t, method="lbs"))
    diag = bounding_diagonal(model.mesh.V)
    np.testing.assert_allclose(browser.positions(0, 1.3), np.asarray(skin(1.3)), rtol=0, atol=1e-4 * diag)


def test_a_rigged_model_is_shown_through_its_glb(browser, tmp_path):
    """``deform.view(model)`` of a RiggedModel in memory (``to_glb``): deform's writer, three.js's reader."""
    model = deform.default_arm()
    page = deform.view(model)
    state = _show(browser, page, tmp_path)
    assert state["meshes"][0]["vertexCount"] == model.mesh.num_vertices
    assert [c["name"] for c in state["clips"]] == [c.name for c in model.clips]
    skin = jax.jit(lambda t: deform.skin_model(model, t, method="lbs"))
    diag = bounding_diagonal(model.mesh.V)
    t = 0.6 * float(model.clip(0).end)
    np.testing.assert_allclose(browser.positions(0, t), np.asarray(skin(t)), rtol=0, atol=1e-4 * diag)
    assert np.abs(browser.positions(0, t) - browser.positions(0, 0.0)).max() > 0.02 * diag


@pytest.mark.slow
def test_gltfs_side_by_side_each_play_their_clip(browser, tmp_path):
    """Three glTFs laid out along x without overlap; a clip name plays in every glTF that has it, the others rest."""
    paths = [DATA / "CesiumMan.glb", DATA / "RiggedSimple.glb", DATA / "CesiumMan.glb"]
    page = deform.view(*paths)
    state = _show(browser, page, tmp_path)
    _compare_counts(state, page)
    assert [c["name"] for c in state["clips"]] == ["Anim_0", "animation_0"]
    man, simple = deform.load_model(paths[0]), deform.load_model(paths[1])
    skin_man = jax.jit(lambda t: deform.skin_model(man, t, method="lbs"))
    skin_simple = jax.jit(lambda t: deform.skin_model(simple, t, method="lbs"))
    diag = bounding_diagonal(man.mesh.V)
    t = 0.8
    for k in (0, 2):
        np.testing.assert_allclose(browser.positions(k, t), np.asarray(skin_man(t)), rtol=0, atol=1e-4 * diag)
    assert browser.call("return v.setClip(1);") == 1
    diag = bounding_diagonal(simple.mesh.V)
    np.testing.assert_allclose(browser.positions(1, t), np.asarray(skin_simple(t)), rtol=0, atol=1e-4 * diag)
    # drawn where the layout put them: their x-ranges follow each other without overlap
    ranges = []
    for k, mesh in enumerate(browser.state()["meshes"]):
        x = browser.positions(k)[:, 0] + mesh["offset"][0]
        ranges.append((x.min(), x.max()))
    assert all(a[1] < b[0] for a, b in zip(ranges, ranges[1:])), ranges
    box = browser.call("return v.boundingBox();")
    assert box["min"][0] <= ranges[0][0] + 1e-6 and box["max"][0] >= ranges[-1][1] - 1e-6


def _wave(T: int = 12):
    """A tube and T frames of a travelling wave along it."""
    V, F, _, _ = tube(0.2)
    frames = np.stack([V + 0.15 * np.sin(3 * V[:, 2:3] - 0.5 * k) * np.array([1.0, 0.5, 0.0]) for k in range(T)])
    return V, F, frames


def test_an_npy_sequence_plays_its_frames(browser, tmp_path):
    V, F, frames = _wave()
    np.save(tmp_path / "frames.npy", frames)
    trimesh.Trimesh(V, F, process=False).export(tmp_path / "tube.ply")
    fps = 10.0
    page = deform.view(tmp_path / "frames.npy", mesh=tmp_path / "tube.ply", fps=fps)
    state = _show(browser, page, tmp_path)
    _compare_counts(state, page)
    assert state["meshes"][0]["kind"] == "sequence" and state["interpolation"] == "linear"
    assert state["clips"] == [{"name": "frames", "duration": pytest.approx((len(frames) - 1) / fps)}]
    diag = bounding_diagonal(frames.reshape(-1, 3))
    for k in (0, 5, len(frames) - 1):
        np.testing.assert_allclose(browser.positions(0, k / fps), frames[k], rtol=0, atol=1e-4 * diag)
        assert browser.state()["frame"] == k
    # between two frames: linear interpolation
    halfway = browser.positions(0, 5.5 / fps)
    np.testing.assert_allclose(halfway, (frames[5] + frames[6]) / 2, rtol=0, atol=1e-4 * diag)
    assert np.abs(frames[6] - frames[0]).max() > 0.05 * diag
    assert _drawn_fraction(browser) > 0.01


def test_npy_files_of_single_frames_form_one_sequence(browser, tmp_path):
    V, F, frames = _wave(3)
    files = []
    for k, frame in enumerate(frames):
        files.append(tmp_path / f"frame{k}.npy")
        np.save(files[-1], frame)
    page = deform.view(*files, mesh=(V, F), fps=1.0)
    state = _show(browser, page, tmp_path)
    assert len(state["meshes"]) == 1 and state["duration"] == pytest.approx(2.0)
    diag = bounding_diagonal(frames.reshape(-1, 3))
    np.testing.assert_allclose(browser.positions(0, 2.0), frames[2], rtol=0, atol=1e-4 * diag)


def _tet_cube(n: int = 2):
    """The unit cube as an n x n x n grid of cells, six tetrahedra each (Kuhn's subdivision), positively oriented."""
    g = np.linspace(0, 1, n + 1)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    index = np.arange((n + 1) ** 3).reshape(n + 1, n + 1, n + 1)
    T = []
    paths = [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]
    for i, j, k in np.ndindex(n, n, n):
        for path in paths:
            corner = np.array([i, j, k])
            chain = [corner.copy()]
            for axis in path:
                corner[axis] += 1
                chain.append(corner.copy())
            T.append([index[tuple(c)] for c in chain])
    T = np.array(T)
    a, b, c, d = (X[T[:, m]] for m in range(4))
    negative = np.einsum("ij,ij->i", np.cross(b - a, c - a), d - a) < 0
    T[negative] = T[negative][:, [0, 2, 1, 3]]
    return X, T


def test_vtu_frames_of_tets_and_of_breaking_triangles(browser, tmp_path):
    """A folder of frame_XXXX.vtu tets (as ``jaxcga fem`` writes) is drawn by its boundary; triangle frames whose
    triangles change (as ``jaxcga xfem`` writes when pieces break apart) switch mesh at that frame."""
    X, T = _tet_cube(2)
    run = tmp_path / "run"
    run.mkdir()
    frames = [X + np.array([0.0, 0.0, 0.1 * k]) * X[:, :1] for k in range(4)]
    for k, x in enumerate(frames):  # named as fem numbers its frames, 0, 10, ...: numeric order, not text order
        meshio.write(run / f"frame_{10 * k:04d}.vtu", meshio.Mesh(x, [("tetra", T)]))
    V, F = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float), np.array([[0, 1, 2], [1, 3, 2]])
    split = np.concatenate([V[F[0]], V[F[1]] + [0.2, 0.2, 0]])  # the two triangles apart, three vertices each
    meshio.write(tmp_path / "a.vtu", meshio.Mesh(V, [("triangle", F)]))
    meshio.write(tmp_path / "b.vtu", meshio.Mesh(split, [("triangle", np.arange(6).reshape(2, 3))]))
    (tmp_path / "broken").mkdir()
    for k, name in enumerate(["a", "a", "b"]):
        (tmp_path / "broken" / f"frame_{k:04d}.vtu").write_bytes((tmp_path / f"{name}.vtu").read_bytes())

    page = deform.view(run, tmp_path / "broken", fps=1.0)
    state = _show(browser, page, tmp_path)
    _compare_counts(state, page)
    cube = state["meshes"][0]
    assert cube["kind"] == "sequence" and cube["vertexCount"] == len(X)
    assert cube["triangleCount"] == 6 * 4 * 2  # the cube's six faces, 2 x 2 squares of two triangles
    diag = bounding_diagonal(np.concatenate(frames))
    for k in range(4):
        np.testing.assert_allclose(browser.positions(0, k), frames[k], rtol=0, atol=1e-4 * diag)
    np.testing.assert_allclose(browser.positions(1, 1.0), V, rtol=0, atol=1e-4 * 2)
    np.testing.assert_allclose(browser.positions(1, 2.0), split, rtol=0, atol=1e-4 * 2)
    assert browser.state()["meshes"][1]["vertexCount"] == 4  # the count of the first frame, as written
    assert _drawn_fraction(browser) > 0.01


def test_a_list_of_meshes_plays_as_frames_whose_triangles_change(browser, tmp_path):
    """``deform.view([(V0, F0), (V1, F1), ...])``, as notebook 07 shows an XFEM run: one frame per pair, the
    triangles switching where the pieces change; each triangle given with its own three vertices (as XFEM writes
    them), the vertices that coincide in every frame of a topology are drawn once."""
    V, F = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float), np.array([[0, 1, 2], [1, 3, 2]])
    lifted = V + [0.0, 0.0, 0.5]
    apart = np.concatenate([lifted[F[0]], lifted[F[1]] + [0.2, 0.2, 0]])  # three vertices each, apart
    own = np.arange(6).reshape(2, 3)
    # (the last frame's triangles are listed from another corner: a new topology, whose corners do not coincide)
    page = deform.view([(V[F].reshape(6, 3), own), (lifted[F].reshape(6, 3), own), (apart, own[:, [1, 2, 0]])], fps=2.0)
    state = _show(browser, page, tmp_path)
    _compare_counts(state, page)
    assert state["meshes"][0]["vertexCount"] == 4  # the shared edge's two corners merged
    assert state["duration"] == 1.0 and state["meshes"][0]["kind"] == "sequence"  # three frames, 2 per second
    np.testing.assert_allclose(browser.positions(0, 0.25), (V + lifted) / 2, rtol=0, atol=1e-4 * 2)
    np.testing.assert_allclose(browser.positions(0, 1.0), apart, rtol=0, atol=1e-4 * 2)  # six vertices now


def _tinted(browser) -> tuple[float, float]:
    """Fractions of the drawing area's pixels that are clearly red-brown (palette 0, 0xc8a27a) and clearly blue
    (palette 1, 0x7aa2c8)."""
    image = browser.screenshot()[:-80].astype(int)
    return float((image[..., 0] - image[..., 2] > 30).mean()), float((image[..., 2] - image[..., 0] > 30).mean())


def test_groups_of_triangles_are_drawn_in_their_own_colours(browser, tmp_path):
    """(V, F, groups) triples: the pieces of a cut body, each in its own colour, its frames played as the pairs';
    without groups the whole sequence takes one colour."""
    V, F = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float), np.array([[0, 1, 2], [1, 3, 2]])
    apart = np.concatenate([V[F[0]], V[F[1]] + [0.5, 0.5, 0]])  # two triangles, three vertices each
    own = np.arange(6).reshape(2, 3)
    frames = [(apart, own, np.array([0, 1])), (apart + [0.0, 0.0, 0.5], own, np.array([0, 1]))]
    state = _show(browser, deform.view(frames, fps=1.0), tmp_path)
    assert state["duration"] == 1.0 and state["meshes"][0]["vertexCount"] == 6
    np.testing.assert_allclose(browser.positions(0, 1.0), apart + [0.0, 0.0, 0.5], rtol=0, atol=1e-4 * 2)
    brown, blue = _tinted(browser)
    assert brown > 0.01 and blue > 0.01
    _show(browser, deform.view([(V, F) for V, F, _ in frames], fps=1.0), tmp_path, "plain.html")
    brown, blue = _tinted(browser)
    assert brown > 0.01 and blue == 0.0


def test_skin_weights_of_a_joint_and_the_skeleton(browser, tmp_path):
    model = deform.load_model(DATA / "CesiumMan.glb")
    j = 3
    name = model.skeleton.names[model.mesh.joints[j]]
    page = deform.view(DATA / "CesiumMan.glb", joint=name)
    state = _show(browser, page, tmp_path)
    assert state["joint"] == name
    J, W = np.asarray(model.mesh.J), np.asarray(model.mesh.W)
    expected = int(((J == j) & (W > 0)).any(axis=1).sum())
    assert 0 < expected < len(J)
    browser.call("v.pause(); v.setTime(0.5); return null;")
    coloured = browser.screenshot()
    assert browser.call(f"return v.showWeights({j});") == expected
    assert browser.call("return v.showWeights(null);") == 0
    plain = browser.screenshot()
    assert (np.abs(coloured.astype(int) - plain).max(axis=-1) > 30).mean() > 0.002
    browser.call("v.showSkeleton(true); return null;")
    skeleton = browser.screenshot()
    assert (np.abs(skeleton.astype(int) - plain).max(axis=-1) > 30).mean() > 0.0005
    browser.call("v.showSkeleton(false); v.setWireframe(true); return null;")
    wire = browser.screenshot()
    assert (np.abs(wire.astype(int) - plain).max(axis=-1) > 30).mean() > 0.002
    assert browser.state()["errors"] == []


def test_playing_advances_time_and_loops(browser, tmp_path):
    _, F, frames = _wave(4)
    state = _show(browser, deform.view((frames, F), fps=20.0), tmp_path)  # a 0.15 s clip: loops several times a second
    assert state["playing"] and state["duration"] == pytest.approx(0.15)
    seen, times, end = set(), [], time.monotonic() + 20
    while not (len(seen) > 1 and any(b < a for a, b in zip(times, times[1:]))) and time.monotonic() < end:
        state = browser.state()
        seen.add(state["frame"])
        times.append(state["time"])
        time.sleep(0.02)
    assert len(seen) > 1 and any(b < a for a, b in zip(times, times[1:])), times  # it advanced, and looped
    browser.call("v.setLoop(false); v.play(); return null;")
    end = time.monotonic() + 20
    while browser.state()["playing"] and time.monotonic() < end:
        time.sleep(0.02)
    state = browser.state()
    assert not state["playing"] and state["time"] == pytest.approx(0.15) and state["frame"] == 3
    assert state["fps"] > 0 and state["rendered"] > 1


def _corrupt(html: str, block: int, text: Callable[[str], str]) -> str:
    start = html.index(f'id="jaxcga-block-{block}">') + len(f'id="jaxcga-block-{block}">')
    end = html.index("</script>", start)
    return html[:start] + text(html[start:end]) + html[end:]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda p: _corrupt(p, 0, lambda b: b[: len(b) // 2]), "three.js cannot load this glTF"),
        (lambda p: _corrupt(p, 0, lambda b: "#" + b[1:]), "not valid base64"),
        (lambda p: p.replace('id="jaxcga-block-0"', 'id="elsewhere"'), "data block 0 is missing"),
    ],
)
def test_a_corrupted_glb_page_shows_its_error(browser, tmp_path, make, message):
    page = deform.view(DATA / "RiggedSimple.glb")
    path = tmp_path / "broken.html"
    path.write_text(make(page.html))
    state = browser.open(path)
    assert not state["ready"] and len(state["errors"]) >= 1 and message in state["errors"][0], state["errors"]
    box = browser.driver.find_element("id", "errors")
    assert box.is_displayed() and message in box.text


def test_a_corrupted_sequence_page_shows_its_error(browser, tmp_path):
    V, F, frames = _wave(3)
    page = deform.view((frames, F))
    path = tmp_path / "broken.html"
    path.write_text(_corrupt(page.html, 1, lambda b: b[: 4 * (len(b) // 8)]))  # half of the positions
    state = browser.open(path)
    expected = len(frames) * len(V) * 6
    assert re.search(rf"data block 1 holds \d+ bytes, expected {expected}", " ".join(state["errors"])), state
    assert browser.driver.find_element("id", "errors").is_displayed()


@pytest.mark.slow
def test_the_outputs_of_skin_fem_and_xfem_are_shown(browser, tmp_path):
    """What the command line writes, shown as written: ``skin``'s .npy with the model as its mesh, ``fem``'s tet
    frames and ``xfem``'s piece surfaces."""
    from jaxcga_cli.main import main

    model = DATA / "CesiumMan.glb"
    assert main(["skin", str(model), "--time", "0.5", "--out", str(tmp_path / "posed.npy")]) == 0
    assert main(["fem", "bar", "--steps", "4", "--every", "2", "--no-figures", "--out", str(tmp_path / "fem")]) == 0
    xfem_run = tmp_path / "xfem"
    assert main(["xfem", "cheese", "--size", "small", "--steps", "3", "--no-figures", "--out", str(xfem_run)]) == 0
    posed = np.load(tmp_path / "posed.npy")
    page = deform.view(tmp_path / "posed.npy", tmp_path / "fem", xfem_run, mesh=model)
    state = _show(browser, page, tmp_path)
    _compare_counts(state, page)
    assert [m["kind"] for m in state["meshes"]] == ["static", "sequence", "sequence"]
    np.testing.assert_allclose(browser.positions(0, 0.0), posed, rtol=0, atol=1e-4 * bounding_diagonal(posed))
    fem_frames = sorted((tmp_path / "fem").glob("frame_*.vtu"))
    last = meshio.read(fem_frames[-1]).points
    t = (len(fem_frames) - 1) / 30.0
    np.testing.assert_allclose(browser.positions(1, t), last, rtol=0, atol=1e-4 * bounding_diagonal(last))
    assert _drawn_fraction(browser) > 0.01


def test_the_notebook_form_renders_in_its_sandboxed_iframe(browser, tmp_path):
    """``_repr_html_`` (what Jupyter shows): the same page in an iframe that may run scripts and nothing else;
    a textured glTF (its image decoded from the embedded data) loads there too."""
    page = deform.view(DATA / "CesiumMan.glb")
    host = tmp_path / "notebook.html"
    host.write_text(f"<!DOCTYPE html><html><body><p>a notebook cell</p>{page._repr_html_()}</body></html>")
    browser.driver.get(host.as_uri())
    browser.driver.switch_to.frame(browser.driver.find_element("tag name", "iframe"))
    try:
        deadline = time.monotonic() + 60
        state = browser.state()
        while not (state["ready"] or state["errors"]) and time.monotonic() < deadline:
            time.sleep(0.05)
            state = browser.state()
        assert state["ready"] and state["errors"] == [], state["errors"]
        assert state["meshes"][0]["vertexCount"] == page.meshes[0]["vertexCount"]
        assert browser.call("return document.querySelector('canvas').height;") > 100
    finally:
        browser.driver.switch_to.default_content()


@pytest.mark.slow
def test_the_demo_page_plays_the_arm_cut_torn_and_drilled(browser, tmp_path, capsys):
    from jaxcga_cli.main import main

    assert main(["demo", "--out", str(tmp_path), "--no-figure"]) == 0
    assert capsys.readouterr().err == ""  # the demo tells its own story: no other command's status lines
    state = browser.open(tmp_path / "demo.html")
    assert state["errors"] == [] and state["ready"], state["errors"]
    names = ["default_arm", "arm_cut_upper", "arm_cut_lower", "arm_torn.glb", "arm_drilled.glb"]
    assert [m["name"] for m in state["meshes"]] == names and {m["kind"] for m in state["meshes"]} == {"skinned"}
    # each model's name under it, left to right as they stand, inside the drawing area, which they fill
    labels = state["labels"]
    width, height = browser.screenshot().shape[1], browser.screenshot().shape[0] - 64
    assert [label["name"] for label in labels] == names
    xs = [label["x"] for label in labels]
    assert xs == sorted(xs) and all(0 < label["x"] < width and 0 < label["y"] < height for label in labels)
    assert xs[-1] - xs[0] > 0.6 * width  # the middles of the first and last models' boxes
    assert [c["name"] for c in state["clips"]] == ["wave"] and state["playing"]
    # every piece plays the arm's clip; the whole models equal deform's skinning of the files written
    models = [deform.default_arm(), *(deform.load_model(tmp_path / name) for name in names[3:])]
    diag = bounding_diagonal(models[0].mesh.V)
    for index, model in zip((0, 3, 4), models, strict=True):
        shown = browser.positions(index, 1.0)
        np.testing.assert_allclose(shown, np.asarray(deform.skin_model(model, 1.0, "lbs")), rtol=0, atol=1e-4 * diag)
    for index in range(len(names)):
        assert np.abs(browser.positions(index, 1.0) - browser.positions(index, 0.0)).max() > 0.02 * diag
    assert _drawn_fraction(browser) > 0.01
