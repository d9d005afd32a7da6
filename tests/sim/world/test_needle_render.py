"""Scene renderer, needle-driving objects (issue 7 part 1, "Scene"): a suture needle as a
thin metallic arc, a tissue pad with an incision line, a gripper's jaws and shaft, and the
needle's ground truth per camera. Each test's docstring names the requirement it checks.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from oralnav.config.scene import load_scene
from oralnav.control.geometry import make_transform, transform_from_euler, transform_points
from oralnav.control.needle.model import Needle
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.sim.world.render import RenderError, SceneRenderer
from oralnav.sim.world.scene import Gripper, Imaging, NeedleObject, Scene, TissuePad

ROOT = Path(__file__).resolve().parents[3]
CT1 = Needle(radius=0.013, wire_diameter=0.001, arc=math.pi)   # seed 002's needle
F = 520.0
# An endoscope-like camera, 640 x 480, with some barrel distortion (the renderer must put
# the wire where the camera model projects it, distortion included).
CAM = CameraModel("endoscope", (640, 480), np.array([[F, 0.0, 318.0], [0.0, F, 242.0],
                                                      [0.0, 0.0, 1.0]]),
                  np.array([-0.12, 0.03, 0.0005, -0.0003, 0.0]))
RIG = Rig(reference="endoscope", cameras={"endoscope": CAM})
CLEAN = Imaging(supersample=2, background=0.0)        # no blur, no noise, black background


def _scene(imaging: Imaging = CLEAN, **objects) -> Scene:
    return Scene(rig=RIG, placements=(), imaging=imaging, **objects)


def _profile(img: np.ndarray, p: np.ndarray, direction: np.ndarray, half: float = 8.0,
             step: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Image values (bilinear) along ``direction`` (unit, px) through ``p`` (px)."""
    ts = np.arange(-half, half + step / 2, step)
    pts = (p + ts[:, None] * direction).astype(np.float32)
    prof = cv2.remap(img.astype(np.float32), pts[:, 0].reshape(1, -1),
                     pts[:, 1].reshape(1, -1), cv2.INTER_LINEAR).ravel()
    return ts, prof


def _normals(uv: np.ndarray) -> np.ndarray:
    """Unit normals (N-2 x 2) of a projected polyline at its interior points."""
    tang = uv[2:] - uv[:-2]
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    return np.stack([-tang[:, 1], tang[:, 0]], axis=1)


def _grasp(T_ref_needle: np.ndarray, phi: float, depth: float = 0.003) -> np.ndarray:
    """T_ref_tool of a gripper holding the needle at arc angle ``phi`` (seed 002, Fig. 3):
    the jaws across the wire (tool y = the needle plane's normal), the gripper's z pointing
    to the arc's centre, the wire ``depth`` behind the tip."""
    radial = np.array([math.cos(phi), math.sin(phi), 0.0])
    z, y = -radial, np.array([0.0, 0.0, 1.0])
    T_N_T = make_transform(np.stack([np.cross(y, z), y, z], axis=1),
                           CT1.radius * radial + depth * z)
    return T_ref_needle @ T_N_T


# -- the needle's image --------------------------------------------------------------------
def test_needle_pixels_lie_on_the_projected_arc():
    """Issue 7 part 1 (needle render): the rendered wire is centred on the camera model's
    projection of the needle's arc (distortion included) to a small fraction of a pixel,
    and is as wide as the wire's projected diameter (within 1 px): the torus segment is
    where and as thick as the needle says. Needle pieces are chords whose sagitta the
    renderer bounds far below a pixel, so no systematic offset may show."""
    T = transform_from_euler([0.004, 0.006, 0.09], [170.0, 15.0, 30.0])
    frame = SceneRenderer(_scene(needles=(NeedleObject("n", CT1, T),))).render()
    img = frame.images["endoscope"]
    truth = frame.needle_truth["endoscope"]["n"]
    uv = truth.points_px
    depth = transform_points(T, CT1.points(len(uv)))[:, 2]
    offsets, width_err = [], []
    for k, n in zip(range(3, len(uv) - 3), _normals(uv)[2:-2], strict=True):
        ts, prof = _profile(img, uv[k], n)
        offsets.append((prof * ts).sum() / prof.sum())   # centroid of the wire's light
        above = np.flatnonzero(prof > 0.25 * 70.0)       # silhouette: half coverage of the
        width_err.append((above[-1] - above[0]) * (ts[1] - ts[0])  # dim edge (level / 2)
                         - CT1.wire_diameter * F / depth[k])
    offsets, width_err = np.abs(offsets), np.abs(width_err)
    assert offsets.mean() < 0.06 and offsets.max() < 0.25, offsets.max()
    assert width_err.max() < 1.0, width_err.max()
    # nothing drawn far from the needle: the background stays exact
    assert np.all(img[:40, :] == 0) and np.all(img[-40:, :] == 0)


def test_needle_shading_has_specular_streaks():
    """Issue 7 part 1 (needle render): a thin metallic arc with specular highlights: with
    the light at the camera, the wire is brightest along its middle where it lies across
    the view, far above its dim base level, and the highlight fades where the wire turns
    toward the camera."""
    T = transform_from_euler([0.0, 0.0, 0.09], [180.0 + 40.0, 0.0, 0.0])  # tilted 40 deg
    nd = NeedleObject("n", CT1, T, level=70.0, specular=180.0, shininess=20.0)
    frame = SceneRenderer(_scene(needles=(nd,))).render()
    img = frame.images["endoscope"]
    uv = frame.needle_truth["endoscope"]["n"].points_px
    tangent = np.stack([-np.sin(np.linspace(0, np.pi, len(uv))),
                        np.cos(np.linspace(0, np.pi, len(uv))), np.zeros(len(uv))], axis=1)
    view = transform_points(T, CT1.points(len(uv)))
    view /= np.linalg.norm(view, axis=1, keepdims=True)
    across = np.abs(np.einsum("ij,ij->i", tangent @ T[:3, :3].T, view))  # |t . v|
    peak = np.array([_profile(img, uv[k], n, half=4.0)[1].max()
                     for k, n in zip(range(1, len(uv) - 1), _normals(uv), strict=True)])
    across = across[1:-1]
    assert peak[across < 0.1].min() > 180.0      # a highlight where the wire lies across
    assert peak[across > 0.55].max() < 120.0     # none where it turns toward the camera


# -- ground truth --------------------------------------------------------------------------
@pytest.fixture(scope="module")
def example() -> tuple[Scene, SceneRenderer]:
    scene = load_scene(ROOT / "config" / "examples" / "needle_pad.toml")
    return scene, SceneRenderer(scene)


def test_truth_is_the_camera_models_projection(example):
    """Issue 7 part 1 (ground truth): every frame records each needle's pose in every
    camera and the projection of K arc points, exactly CameraModel's projection of
    Needle.points(K) through that pose (the shipped example: the endoscope rig with strong
    barrel distortion); render(poses=...) moves the needle by name and the truth follows."""
    scene, renderer = example
    cam = scene.rig["endoscope"]
    nd = scene.needles[0]
    T_moved = nd.T_ref_needle @ transform_from_euler([0.002, -0.001, 0.0], [0.0, 0.0, 20.0])
    for poses in ({}, {nd.name: T_moved}):
        frame = renderer.render(poses=poses)
        T_ref = poses.get(nd.name, nd.T_ref_needle)
        np.testing.assert_array_equal(frame.T_ref_needle[nd.name], T_ref)
        truth = frame.needle_truth["endoscope"][nd.name]
        np.testing.assert_allclose(truth.T_cam_needle, cam.T_cam_ref @ T_ref, atol=1e-15)
        K = renderer.needle_points
        assert K == 64 and truth.points_px.shape == (K, 2)
        np.testing.assert_allclose(truth.phi, np.linspace(0.0, np.pi, K))
        expected = cam.project_from(truth.T_cam_needle, nd.needle.points(K))
        np.testing.assert_allclose(truth.points_px, expected, atol=1e-9)
        assert truth.visible.all() and truth.visible_fraction == 1.0   # on the pad, in view
    doc = frame.truth_json("endoscope", {"endoscope": "endoscope.png"})
    entry = doc["cameras"]["endoscope"]["needles"][nd.name]
    assert entry["visible_fraction"] == 1.0 and len(entry["points_px"]) == 64
    assert doc["needles"][nd.name]["T_ref_needle"] == T_moved.tolist()
    assert set(doc["pads"]) == {"pad"} and set(doc["grippers"]) == {"driver"}
    assert doc["cameras"]["endoscope"]["fields"] == {}


@pytest.mark.parametrize("facing", [True, False], ids=["normal_to_camera", "normal_away"])
def test_jaws_hide_the_needle_where_they_cover_it(facing):
    """Issue 7 part 1 (visibility): a gripper holding the needle, seen across its jaws:
    the near jaw hides the wire over the jaw's width, and the visibility flags drop for
    exactly the arc points under it, whichever side the camera sees the grasp from (one
    jaw is in front of the wire, the other behind it: only a per-sample depth test gets
    both right); the image shows the jaw there and the needle beside it."""
    T_N = transform_from_euler([0.0, 0.0, 0.085], [180.0 if facing else 0.0, 0.0, 0.0])
    g = Gripper("grip", _grasp(T_N, 1.2), jaw_width=0.0025, jaw_thickness=0.0012,
                opening=CT1.wire_diameter, shaft_length=0.03, level=110.0)
    nd = NeedleObject("n", CT1, T_N)
    frame = SceneRenderer(_scene(needles=(nd,), grippers=(g,))).render()
    truth = frame.needle_truth["endoscope"]["n"]
    # where each arc point lies across the jaws (tool x; the jaw spans |x| <= width / 2)
    x_tool = transform_points(np.linalg.inv(g.T_ref_tool) @ T_N,
                              CT1.points(len(truth.phi)))[:, 0]
    under = np.abs(x_tool) < 0.5 * g.jaw_width - 0.0002
    clear = np.abs(x_tool) > 0.5 * g.jaw_width + 0.0004
    assert under.sum() >= 3
    assert not truth.visible[under].any()
    assert truth.visible[clear].all()
    assert truth.visible_fraction == pytest.approx(1 - (~truth.visible).sum() / 64)
    img = frame.images["endoscope"].astype(float)
    at = np.rint(truth.points_px).astype(int)
    jaw_px = img[at[under, 1], at[under, 0]]
    assert np.all(np.abs(jaw_px - 110.0) < 15.0)    # the jaw face (rods' shading, ~face-on)
    wire_px = img[at[clear, 1], at[clear, 0]]
    assert np.median(wire_px) > 120.0                # the wire, with its highlight


# -- the pad -------------------------------------------------------------------------------
PAD_T = transform_from_euler([0.0, 0.002, 0.095], [180.0 + 35.0, 0.0, 10.0])  # tilted 35 deg
PAD = TissuePad("pad", PAD_T, size=(0.05, 0.04), level=170.0,
                incision=((-0.02, -0.012), (0.02, -0.008)), incision_width=0.0008,
                incision_level=35.0)


def test_incision_is_drawn_where_it_should_be():
    """Issue 7 part 1 (pad): the pad is drawn at its level over its rectangle, with a dark
    straight incision line exactly on the projection of its ends (the line's darkness is
    centred on the projected line to a small fraction of a pixel, about as wide as the
    projected incision width, and ends at its ends)."""
    frame = SceneRenderer(_scene(pads=(PAD,))).render()
    img = frame.images["endoscope"].astype(np.float32)
    (ax, ay), (bx, by) = PAD.incision
    t = np.linspace(0.1, 0.9, 17)
    line = np.stack([ax + t * (bx - ax), ay + t * (by - ay), 0 * t], axis=1)
    uv = CAM.project_from(PAD_T, line)
    d = uv[-1] - uv[0]
    d /= np.linalg.norm(d)
    across = np.array([-d[1], d[0]])
    offsets = []
    for p in uv:
        ts, prof = _profile(img, p, across, half=6.0)
        dark = PAD.level - prof
        offsets.append(abs((dark * ts).sum() / dark.sum()))
        assert abs(prof[0] - PAD.level) < 1.0 and abs(prof[-1] - PAD.level) < 1.0
        assert prof.min() < PAD.incision_level + 20.0
    # hard-edged 4 px stroke, 2 x 2 samples a pixel, no blur: edges quantised to 1/4 px
    assert np.mean(offsets) < 0.1 and max(offsets) < 0.25, offsets
    # the projected incision width is about 0.8 mm * F / depth ~ 4 px: dark ~ that wide
    ts, prof = _profile(img, uv[8], across, half=6.0)
    z = transform_points(PAD_T, line[8:9])[0, 2]
    width = (PAD.level - prof).sum() * (ts[1] - ts[0]) / (PAD.level - PAD.incision_level)
    assert width == pytest.approx(PAD.incision_width * F / z, rel=0.35)  # foreshortened
    # past its ends the pad is plain
    ends = CAM.project_from(PAD_T, np.array([[ax, ay, 0.0], [bx, by, 0.0]]))
    for e, out in ((ends[0], -d), (ends[1], d)):
        q = np.rint(e + 4.0 * out).astype(int)
        assert abs(img[q[1], q[0]] - PAD.level) < 1.0
        q = np.rint(e - 3.0 * out).astype(int)
        assert img[q[1], q[0]] < PAD.level - 60.0


def test_needle_lying_on_a_tilted_pad_is_drawn_over_it():
    """Issue 7 part 1 (depth compositing): a needle lying on the far half of a steeply
    tilted pad, deeper than the pad's mean depth, is drawn over the pad and fully visible;
    a needle half driven into the pad shows only its part above the surface, and the truth
    flags the part under the surface as hidden."""
    # on the far half (pad y < 0 for this tilt), the arc's body toward -y
    T_on = PAD_T @ transform_from_euler([0.0, -0.004, 0.0005], [0.0, 0.0, 180.0])
    assert transform_points(T_on, CT1.points(64))[:, 2].mean() > PAD_T[2, 3] + 0.003
    bare = SceneRenderer(_scene(pads=(PAD,))).render().images["endoscope"].astype(float)
    frame = SceneRenderer(_scene(pads=(PAD,), needles=(NeedleObject("n", CT1, T_on),))
                          ).render()
    truth = frame.needle_truth["endoscope"]["n"]
    assert truth.visible.all()
    at = np.rint(truth.points_px).astype(int)
    diff = np.abs(frame.images["endoscope"].astype(float) - bare)[at[:, 1], at[:, 0]]
    assert np.mean(diff > 20.0) > 0.9
    # half driven: the needle upright in the pad's x-z plane, its body down into the
    # tissue (needle y = -pad z), its centre 5 mm above the surface: the arc dips 8 mm
    # below it, base and tip stand out
    T_driven = PAD_T @ make_transform(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0],
                                                [0.0, -1.0, 0.0]]), [0.0, 0.004, 0.005])
    frame = SceneRenderer(_scene(pads=(PAD,), needles=(NeedleObject("n", CT1, T_driven),))
                          ).render()
    truth = frame.needle_truth["endoscope"]["n"]
    height = transform_points(np.linalg.inv(PAD_T) @ T_driven, CT1.points(64))[:, 2]
    assert (height < -0.001).sum() >= 5 and (height > 0.001).sum() >= 5
    assert not truth.visible[height < -0.0005].any()
    assert truth.visible[height > 0.0005].all()
    img = frame.images["endoscope"].astype(float)
    at = np.rint(truth.points_px[height < -0.002]).astype(int)
    assert np.all(np.abs(img[at[:, 1], at[:, 0]] - bare[at[:, 1], at[:, 0]]) < 1.0)


# -- determinism, speed, bad input ---------------------------------------------------------
NOISY = Imaging(supersample=2, background=30.0, blur_sigma_px=1.0, read_noise_dn=1.5,
                shot_noise_gain=0.06, illumination_gradient=(0.3, 0.2))


def _full_scene(imaging: Imaging = NOISY, seed: int = 4) -> Scene:
    T_N = PAD_T @ transform_from_euler([0.003, 0.0, 0.0005], [0.0, 0.0, 30.0])
    grip = Gripper("grip", PAD_T @ transform_from_euler([-0.012, 0.004, 0.01],
                                                         [200.0, -20.0, 0.0]), opening=0.003)
    return Scene(rig=RIG, placements=(), imaging=imaging, seed=seed,
                 needles=(NeedleObject("n", CT1, T_N),), pads=(PAD,), grippers=(grip,))


def test_same_seed_same_bytes():
    """Issue 7 part 1 (renderer guarantees): a needle + pad + gripper scene with blur,
    noise and an illumination gradient renders to the same bytes and truth for the same
    seed and frame; the noise changes with the frame."""
    a = SceneRenderer(_full_scene()).render(frame=2)
    b = SceneRenderer(_full_scene()).render(frame=2)
    assert a.images["endoscope"].tobytes() == b.images["endoscope"].tobytes()
    assert a.truth_json("endoscope") == b.truth_json("endoscope")
    c = SceneRenderer(_full_scene()).render(frame=3)
    assert c.images["endoscope"].tobytes() != a.images["endoscope"].tobytes()


def test_state_rendered_again_gets_a_full_renders_bytes():
    """Issue 36 item 3 (per-trial cost): a state rendered again (poses and jaw gaps
    unchanged) reuses its noise-free render, and its frame is byte for byte what a fresh
    renderer gives, noise and truth included; any moved pose or jaw gap renders anew, and
    a caller changing a frame's truth does not change a later frame's."""
    scene = _full_scene()
    grip = scene.grippers[0]
    moved = {"grip": grip.T_ref_tool @ transform_from_euler([0.0, 0.0, 2e-6], [0, 0, 0])}
    states = [({}, {}), (moved, {}), ({}, {}), ({}, {"grip": 0.002}), (moved, {})]
    renderer = SceneRenderer(scene, keep_clean=3)
    full = renderer._render_clean
    calls = []
    renderer._render_clean = lambda *a: calls.append(1) or full(*a)
    for frame, (poses, openings) in enumerate(states):
        got = renderer.render(poses=poses, frame=frame, openings=openings)
        want = SceneRenderer(scene).render(poses=poses, frame=frame, openings=openings)
        assert got.images["endoscope"].tobytes() == want.images["endoscope"].tobytes()
        assert got.truth_json("endoscope") == want.truth_json("endoscope")
        got.needle_truth["endoscope"]["n"].visible[:] = False
    assert len(calls) == 3  # the third and the fifth states were rendered before
    plain = SceneRenderer(scene)  # by default each render is a full one (a camera's time)
    full_plain = plain._render_clean
    calls.clear()
    plain._render_clean = lambda *a: calls.append(1) or full_plain(*a)
    plain.render(frame=0)
    plain.render(frame=1)
    assert len(calls) == 2
    with pytest.raises(RenderError, match="keep_clean"):
        SceneRenderer(scene, keep_clean=-1)


def test_render_time_guard():
    """Issue 7 part 1 (speed): a 640 x 480 endoscope frame with a needle, a pad and a
    gripper (supersample 2, blur, noise) renders well within 100 ms median (about 10 ms
    on the 2-core development machine; loose for loaded CI machines)."""
    renderer = SceneRenderer(_full_scene())
    renderer.prepare()
    renderer.render()
    times = []
    for k in range(7):
        t0 = time.perf_counter()
        renderer.render(frame=k)
        times.append(time.perf_counter() - t0)
    assert np.median(times) < 0.1, times


def test_bad_objects_are_refused():
    """Issue 7 part 1 (bad input): objects sharing a name, a pad of no size, a gripper
    with a negative opening, and poses for unknown objects are refused with a clear
    RenderError."""
    nd = NeedleObject("n", CT1, np.eye(4))
    with pytest.raises(RenderError, match="repeated: \\['n'\\]"):
        SceneRenderer(_scene(needles=(nd,), pads=(replace(PAD, name="n"),)))
    with pytest.raises(RenderError, match="size_x"):
        SceneRenderer(_scene(pads=(replace(PAD, size=(0.0, 0.04)),)))
    with pytest.raises(RenderError, match="opening"):
        SceneRenderer(_scene(grippers=(Gripper("g", np.eye(4), opening=-0.001),)))
    with pytest.raises(RenderError, match="unknown placements or objects"):
        SceneRenderer(_scene(needles=(nd,))).render(poses={"m": np.eye(4)})


def test_example_renders_needle_pad_and_gripper(example):
    """Issue 7 part 1 (example scene): needle_pad.toml renders the endoscope's view with
    the pad (its level around the needle), the needle and the gripper, its needle fully
    visible in ground truth."""
    scene, renderer = example
    frame = renderer.render()
    img = frame.images["endoscope"]
    assert img.dtype == np.uint8 and img.shape == (1080, 1920)
    truth = frame.needle_truth["endoscope"]["ct1"]
    assert truth.visible_fraction == 1.0
    c = np.rint(truth.points_px.mean(axis=0)).astype(int)   # inside the arc: bare pad
    assert 120 < img[c[1], c[0]] < 230
    g = scene.grippers[0]
    tip = scene.rig["endoscope"].project_from(
        scene.rig["endoscope"].T_cam_ref @ g.T_ref_tool,
        np.array([[0.0, 0.5 * g.opening + 0.5 * g.jaw_thickness, -0.002]]))[0]
    q = np.rint(tip).astype(int)
    assert abs(int(img[q[1], q[0]]) - 110) < 40       # a jaw (the gripper's level)


# -- suture thread, jaw openings, long shafts (issue 7, "What to build" items 1 and 4) ----
def _thread_on_pad(length: float = 0.015) -> NeedleObject:
    """The CT-1 needle lying on PAD (its plane the pad's) with a suture thread."""
    T = PAD_T @ transform_from_euler([0.004, -0.004, 0.0005], [0.0, 0.0, 120.0])
    return NeedleObject("n", CT1, T, thread_length=length, thread_level=45.0)


def test_thread_is_drawn_beyond_the_base_and_nowhere_else():
    """Item 1 (suture thread): a needle with a thread renders dark pixels along the
    thread's projection beyond the base (it leaves along -tangent(0) and bends in the
    needle's plane, away from the arc), and changes no pixel anywhere else (none beyond
    the tip); the needle's own truth is unchanged; thread_length 0 renders the needle
    alone, byte for byte."""
    nd = _thread_on_pad()
    with_thread = SceneRenderer(_scene(pads=(PAD,), needles=(nd,))).render()
    without = SceneRenderer(_scene(pads=(PAD,), needles=(replace(nd, thread_length=0.0),))
                            ).render()
    plain = SceneRenderer(_scene(pads=(PAD,), needles=(NeedleObject("n", CT1, nd.T_ref_needle),))
                          ).render()
    assert without.images["endoscope"].tobytes() == plain.images["endoscope"].tobytes()
    img = with_thread.images["endoscope"].astype(float)
    bare = without.images["endoscope"].astype(float)
    pts = nd.thread_points(60)
    # the shape: starts at the base along -tangent(0), bends away from the arc's centre
    np.testing.assert_allclose(pts[0], CT1.base, atol=1e-15)
    d0 = (pts[1] - pts[0]) / np.linalg.norm(pts[1] - pts[0])
    assert d0 @ -CT1.tangent(0.0) > 0.999
    assert np.all(np.diff(pts[:, 0]) >= 0) and np.all(pts[:, 2] == 0)
    length = np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()
    assert length == pytest.approx(0.015, rel=1e-3)
    uv = CAM.project_from(nd.T_ref_needle, pts[5:])                   # clear of the swage
    at = np.rint(uv).astype(int)
    assert np.all(img[at[:, 1], at[:, 0]] < PAD.level - 80.0)
    # every changed pixel lies within 3 px of the thread's projection
    changed = np.argwhere(np.abs(img - bare) > 0.5)[:, ::-1]
    line = CAM.project_from(nd.T_ref_needle, nd.thread_points(400))
    dist = np.linalg.norm(changed[:, None, :] - line[None], axis=2).min(axis=1)
    assert len(changed) > 50 and dist.max() < 3.0
    tip = transform_points(nd.T_ref_needle, CT1.tip[None] + np.linspace(0.001, 0.015, 15)[:, None]
                           * CT1.tangent(CT1.arc)[None])
    q = np.rint(CAM.project(tip)).astype(int)
    np.testing.assert_array_equal(img[q[:, 1], q[:, 0]], bare[q[:, 1], q[:, 0]])
    a, b = with_thread.needle_truth["endoscope"]["n"], without.needle_truth["endoscope"]["n"]
    np.testing.assert_array_equal(a.visible, b.visible)
    assert a.visible.all()


def test_thread_is_hidden_under_the_pad_and_by_the_jaws():
    """Item 1 (suture thread): the thread shares the needle's and grippers' depth buffer:
    where it runs below the pad's surface the pad shows (no pixel changes there), and a
    gripper between it and the camera hides it."""
    # the needle upright on the pad, its body up, its base 2 mm above the surface: the
    # thread leaves the base straight down into the tissue
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    T = PAD_T @ make_transform(R, [0.0, 0.004, 0.002])
    nd = NeedleObject("n", CT1, T, thread_length=0.015)
    pts = nd.thread_points(200)
    height = transform_points(np.linalg.inv(PAD_T) @ T, pts)[:, 2]
    assert (height < -0.001).sum() > 150 and (height > 0.0005).sum() >= 5
    img = SceneRenderer(_scene(pads=(PAD,), needles=(nd,))).render().images["endoscope"]
    bare = SceneRenderer(_scene(pads=(PAD,), needles=(replace(nd, thread_length=0.0),))
                         ).render().images["endoscope"]
    q = np.rint(CAM.project_from(T, pts[height < -0.0008])).astype(int)
    np.testing.assert_array_equal(img[q[:, 1], q[:, 0]], bare[q[:, 1], q[:, 0]])
    # a gripper 3 mm above a thread point on a flat needle, between it and the camera
    flat = _thread_on_pad()
    p = transform_points(flat.T_ref_needle, flat.thread_points(10)[6:7])[0]
    normal = PAD_T[:3, 2]
    z = -normal
    x = np.cross(PAD_T[:3, 1], z)
    x /= np.linalg.norm(x)
    jaw = Gripper("g", make_transform(np.column_stack([x, np.cross(z, x), z]), p + 0.003 * normal),
                  opening=0.0, jaw_width=0.004, jaw_thickness=0.002, shaft_length=0.02)
    with_t = SceneRenderer(_scene(pads=(PAD,), needles=(flat,), grippers=(jaw,))).render()
    no_t = SceneRenderer(_scene(pads=(PAD,), needles=(replace(flat, thread_length=0.0),),
                                grippers=(jaw,))).render()
    u = np.rint(CAM.project(p[None])[0]).astype(int)
    window = (slice(u[1] - 1, u[1] + 2), slice(u[0] - 1, u[0] + 2))
    np.testing.assert_array_equal(with_t.images["endoscope"][window],
                                  no_t.images["endoscope"][window])
    # the gripper's matt shading (level 110 times 0.55..1) covers the point
    assert 0.55 * 110.0 - 2.0 <= float(with_t.images["endoscope"][u[1], u[0]]) <= 112.0


def test_render_takes_jaw_openings_by_name():
    """Item 4 (rendering the cell's jaws): render(openings=...) draws a gripper with
    another jaw gap, exactly as a scene whose gripper has that opening, records the gaps
    in the frame, and refuses unknown grippers and negative gaps."""
    scene = _full_scene()
    g = scene.grippers[0]
    a = SceneRenderer(scene).render(frame=1, openings={g.name: 0.001})
    b = SceneRenderer(replace(scene, grippers=(replace(g, opening=0.001),))).render(frame=1)
    c = SceneRenderer(scene).render(frame=1)
    assert a.images["endoscope"].tobytes() == b.images["endoscope"].tobytes()
    assert a.images["endoscope"].tobytes() != c.images["endoscope"].tobytes()
    assert a.opening == {g.name: 0.001} and c.opening == {g.name: g.opening}
    with pytest.raises(RenderError, match="unknown grippers \\['other'\\]"):
        SceneRenderer(scene).render(openings={"other": 0.001})
    with pytest.raises(RenderError, match="finite gap >= 0"):
        SceneRenderer(scene).render(openings={g.name: -0.001})


def test_shaft_reaching_behind_the_camera_is_still_drawn():
    """Item 4 (rendering the cell's arms): a gripper whose shaft runs back past the
    camera's plane (an instrument entering from beside the endoscope, its RCM behind the
    lens) is drawn up to the near plane, not dropped."""
    z = np.array([0.6, 0.0, 0.8])
    x = np.array([0.0, 1.0, 0.0])
    T = make_transform(np.column_stack([x, np.cross(z, x), z]), [0.01, 0.0, 0.09])
    g = Gripper("g", T, shaft_length=0.3, opening=0.003)
    assert transform_points(T, np.array([[0.0, 0.0, -0.31]]))[0, 2] < 0   # behind the lens
    img = SceneRenderer(_scene(grippers=(g,))).render().images["endoscope"]
    on_axis = transform_points(T, np.array([[0.0, 0.0, -0.03], [0.0, 0.0, -0.05]]))
    for u, v in np.rint(CAM.project(on_axis)).astype(int):
        assert img[v, u] > 60                                # the shaft, on black
