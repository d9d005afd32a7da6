"""Tests of the pose covariance's honesty (issue 34 item 6, "single-tag poses claim too
much"): the reported sigma must cover the true error at the stated rate for single ArUco
tags and small marker fields, stay as it was for large fields, and the covariance
watchdog must see what the pose really is.

Each test's docstring names the requirement it checks. The coverage tests render tags and
small ChArUco fields with the scene renderer (blur, read and shot noise), detect them with
the product's detectors and pose them with the product's estimators, over a grid of
distances and tilts. Seeds 10000-10239 (tags) and 20000-20233 (fields) were not used to
choose the noise model: it was set on seeds 0-149 of a random-pose study and checked on
seeds 5000-5299 (numbers in docs/tracking.md).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from oralnav.control.geometry import make_transform
from oralnav.control.vision import pose as pose_module
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.detection import detect_fields
from oralnav.control.vision.markers import MarkerField
from oralnav.control.vision.pose import (
    FIELD_CORNERS,
    MIN_SIGMA_PX,
    CornerNoise,
    Observation,
    _residuals,
    _stack,
    bundle_adjust,
    estimate_pose,
    pixel_variance,
    pose_covariance,
)
from oralnav.control.vision.rigid_body import (
    TAG_CORNERS,
    RigidBody,
    detect_tags,
    estimate_body,
    single_tag_body,
)
from oralnav.safety.watchdogs import CovarianceWatchdog
from oralnav.sim.world.aruco_video import field_body
from oralnav.sim.world.render import SceneRenderer
from oralnav.sim.world.scene import Imaging, Placement, Scene
from tests.helpers import ARUCO_DATA, needs_aruco_data

#: VGA, 600 px focal length, a little barrel distortion (the ``sim aruco`` camera).
CAMERA = CameraModel("cam", (640, 480), np.array([[600.0, 0.0, 320.0], [0.0, 600.0, 240.0],
                                                 [0.0, 0.0, 1.0]]),
                     np.array([-0.08, 0.05, 0.0, 0.0, 0.0]))
RIG = Rig("cam", {"cam": CAMERA})
#: One 30 mm tag (id 0) on a 2 x 2 ChArUco plate: the renderer draws ChArUco sheets.
TAG_PLATE = MarkerField("tagplate", "DICT_4X4_50", (2, 2), 0.04, 0.03)
SMALL_FIELDS = (MarkerField("f43", "DICT_4X4_50", (4, 3), 0.010, 0.0075),   # 6 corners
                MarkerField("f44", "DICT_4X4_50", (4, 4), 0.008, 0.006))    # 9 corners
#: Gaussian optical blur levels (px): a sharp, a typical and a soft lens.
BLURS = (0.5, 0.9, 1.3)
TILTS_DEG = (5.0, 25.0, 45.0)
TAG_SIDES_PX = (32.0, 48.0, 72.0, 100.0)
FIELD_SIDES_PX = (90.0, 130.0, 180.0)   # the sheet's long side in the image
CHI2_1S, CHI2_2S = chi2.ppf(0.6827, 6), chi2.ppf(0.9545, 6)


def _tag_body() -> tuple[RigidBody, np.ndarray]:
    """The plate's tag 0 as a one-tag body centred on the tag, and ``T_plate_tag``."""
    corners = field_body(TAG_PLATE).tags[0]
    centre = corners.mean(axis=0)
    return RigidBody("tag", "DICT_4X4_50", {0: corners - centre}), make_transform(None, centre)


def _renderers(fld: MarkerField) -> list[SceneRenderer]:
    """One renderer per blur level; a render's noise draw follows its frame number."""
    return [SceneRenderer(Scene(rig=RIG, placements=(Placement(fld.name, fld, np.eye(4)),),
                                imaging=Imaging(supersample=2, blur_sigma_px=b,
                                                read_noise_dn=2.0, shot_noise_gain=0.05),
                                seed=34)) for b in BLURS]


def _pose(rng: np.random.Generator, size_m: float, side_px: float, tilt_deg: float
          ) -> np.ndarray:
    """``T_cam_object`` of an object centred on its origin: ``size_m`` spans ``side_px``
    (+-10 %), turned ``tilt_deg`` (+-5) about a random axis in its plane and by a random
    angle within it, its centre anywhere in the middle half of the image."""
    z = CAMERA.K[0, 0] * size_m / (side_px * rng.uniform(0.9, 1.1))
    axis = rng.normal(size=2)
    tilt = np.radians(tilt_deg + rng.uniform(-5.0, 5.0)) * axis / np.linalg.norm(axis)
    R = (Rotation.from_rotvec([tilt[0], tilt[1], 0.0])
         * Rotation.from_euler("z", rng.uniform(-180.0, 180.0), degrees=True)).as_matrix()
    uv = rng.uniform([160.0, 120.0], [480.0, 360.0])
    ray = np.append((uv - CAMERA.K[:2, 2]) / CAMERA.K[0, 0], 1.0)
    return make_transform(R, z * ray)


def _error6(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """[dt (m), dtheta (rad)] in the reference frame, the covariance's parametrisation."""
    dth = Rotation.from_matrix(T_est[:3, :3] @ T_true[:3, :3].T).as_rotvec()
    return np.concatenate([T_est[:3, 3] - T_true[:3, 3], dth])


def _old_covariance(corners: np.ndarray, ob: Observation, T: np.ndarray) -> np.ndarray:
    """The covariance before issue 34: the residual variance with ``2N - 6`` degrees of
    freedom, floored at 0.05 px, times ``(J^T J)^-1``."""

    class Model:
        pass

    model = Model()
    model.corners = corners  # type: ignore[attr-defined]
    X, xy, _, R_cr, t_cr, f = _stack(model, [ob])  # type: ignore[arg-type]
    r, J, _ = _residuals(T, X, xy, R_cr, t_cr, f, True)
    s2 = max(float(r @ r) / max(len(r) - 6, 1), MIN_SIGMA_PX ** 2)
    return s2 * np.linalg.inv(J.T @ J)


class Trials:
    """Errors and covariances over many renders: ``errors`` (n x 6) and ``cov``
    (n x 6 x 6) of the product, ``old_errors`` and ``old_cov`` of the pre-issue-34 model
    (for tags the same pose; for fields the pose without the planar-ambiguity check),
    ``kept`` the render each pose came from (renders with no pose are left out)."""

    def __init__(self, errors, cov, old_errors, old_cov, kept, attempts: int) -> None:
        self.errors = np.asarray(errors)
        self.cov = np.asarray(cov)
        self.old_errors = np.asarray(old_errors)
        self.old_cov = np.asarray(old_cov)
        self.kept = np.asarray(kept)  # the render number of each pose
        self.attempts = attempts

    def _pick(self, old: bool) -> tuple[np.ndarray, np.ndarray]:
        return (self.old_errors, self.old_cov) if old else (self.errors, self.cov)

    def coverage(self, k: float, old: bool = False) -> tuple[float, float]:
        """Fractions of translation and rotation components within ``k`` reported sigma."""
        errors, cov = self._pick(old)
        z = np.abs(errors) / np.sqrt(np.einsum("nii->ni", cov))
        return float(np.mean(z[:, :3] <= k)), float(np.mean(z[:, 3:] <= k))

    def mahalanobis(self, old: bool = False) -> np.ndarray:
        errors, cov = self._pick(old)
        return np.array([e @ np.linalg.solve(c, e) for e, c in zip(errors, cov, strict=True)])

    def worst_rotation_deg(self, old: bool = False) -> float:
        return float(np.degrees(np.linalg.norm(self._pick(old)[0][:, 3:], axis=1)).max())


@pytest.fixture(scope="module")
def tag_trials() -> Trials:
    """240 renders of one 30 mm tag: 4 image sizes (32-100 px sides) x 3 tilts x 20,
    each at one of 3 blurs, seeds 10000-10239."""
    body, T_plate_tag = _tag_body()
    renderers = _renderers(TAG_PLATE)
    errors, cov, old, kept = [], [], [], []
    seed = 10000
    for side in TAG_SIDES_PX:
        for tilt in TILTS_DEG:
            for _ in range(20):
                rng = np.random.default_rng(seed)
                T = _pose(rng, 0.03, side, tilt)
                img = renderers[seed % 3].render({TAG_PLATE.name: T @ np.linalg.inv(
                    T_plate_tag)}, frame=seed).images["cam"]
                seed += 1
                tags = detect_tags(img, "DICT_4X4_50")
                if 0 not in tags:
                    continue
                est = estimate_body(body, {"cam": {0: tags[0]}}, RIG)
                if est is None:
                    continue
                errors.append(_error6(est.T_ref_field, T))
                cov.append(est.covariance)
                old.append(_old_covariance(body.corners(),
                                           Observation(CAMERA, np.arange(4), tags[0]),
                                           est.T_ref_field))
                kept.append(seed - 1 - 10000)
    return Trials(errors, cov, errors, old, kept, seed - 10000)


@pytest.fixture(scope="module")
def field_trials() -> Trials:
    """234 renders of 6- and 9-corner ChArUco fields: 3 image sizes (90-180 px) x 3 tilts
    x 26, each at one of 3 blurs, seeds 20000-20233; one camera, NVG-BA as the tracker
    runs it."""
    renderers = {f.name: _renderers(f) for f in SMALL_FIELDS}
    errors, cov, old_errors, old, kept = [], [], [], [], []
    seed = 20000
    for side in FIELD_SIDES_PX:
        for tilt in TILTS_DEG:
            for _ in range(26):
                rng = np.random.default_rng(seed)
                fld = SMALL_FIELDS[seed % 2]
                size = np.array([*fld.sheet_size, 0.0])
                T_centre = _pose(rng, float(size.max()), side, tilt)
                T = T_centre @ make_transform(None, -0.5 * size)
                img = renderers[fld.name][(seed // 2) % 3].render(
                    {fld.name: T}, frame=seed).images["cam"]
                seed += 1
                found = detect_fields(img, [fld]).get(fld.name)
                if found is None:
                    continue
                rows = np.array([fld.corner_index[int(i)] for i in found.ids])
                ob = Observation(CAMERA, rows, found.px)
                est = estimate_pose(fld, [ob])
                with pytest.MonkeyPatch.context() as mp:  # the fit before issue 34
                    mp.setattr(pose_module, "_planar_ambiguity", lambda T, cov, *a: (T, cov))
                    est_old = estimate_pose(fld, [ob])
                if est is None or est_old is None:
                    continue
                errors.append(_error6(est.T_ref_field, T))
                cov.append(est.covariance)
                old_errors.append(_error6(est_old.T_ref_field, T))
                old.append(_old_covariance(fld.corners, ob, est_old.T_ref_field))
                kept.append(seed - 1 - 20000)
    return Trials(errors, cov, old_errors, old, kept, seed - 20000)


# -- coverage -------------------------------------------------------------------------------
def _report(name: str, tr: Trials) -> str:
    lines = [f"{name}: {len(tr.errors)} poses of {tr.attempts} renders, worst rotation "
             f"error {tr.worst_rotation_deg():.1f} deg (before: "
             f"{tr.worst_rotation_deg(old=True):.1f} deg)"]
    for label, old in (("new", False), ("old", True)):
        d2 = tr.mahalanobis(old)
        (t1, r1), (t2, r2) = tr.coverage(1.0, old), tr.coverage(2.0, old)
        lines.append(f"  {label}: 1 sigma t {t1:.2f} r {r1:.2f}, 2 sigma t {t2:.2f} r {r2:.2f}, "
                     f"6-DOF Mahalanobis within 68/95 %: {np.mean(d2 <= CHI2_1S):.2f} / "
                     f"{np.mean(d2 <= CHI2_2S):.2f}")
    return "\n".join(lines)


def _assert_covers(what: str, tr, mahalanobis_95: float) -> str:
    """The coverage both kinds of trial must show: at least 200 poses; each translation and
    rotation component within 1 sigma in 55-85 % of them and within 2 sigma in >= 90 %;
    the 6-DOF Mahalanobis distance within chi-square's 95 % point in ``mahalanobis_95`` of
    them. Returns the report (printed too)."""
    msg = _report(what, tr)
    print(msg)
    assert len(tr.errors) >= 200, msg
    t1, r1 = tr.coverage(1.0)
    t2, r2 = tr.coverage(2.0)
    assert 0.55 <= t1 <= 0.85 and 0.55 <= r1 <= 0.85, msg
    assert t2 >= 0.90 and r2 >= 0.90, msg
    assert np.mean(tr.mahalanobis() <= CHI2_2S) >= mahalanobis_95, msg
    return msg


def test_single_tag_sigma_covers_its_error(tag_trials):
    """Issue 34 item 6 (single tags): over >= 200 renders of one tag at 4 distances, 3
    tilts and 3 blurs, each translation and rotation component of the true error lies
    within the reported 1 sigma in 55-85 % of poses (a Student-t error of few degrees of
    freedom, scaled to its variance, covers about 75 % at 1 sigma; a Gaussian 68 %) and
    within 2 sigma in >= 90 %; the
    6-DOF Mahalanobis distance is within chi-square's 95 % point in >= 88 %. The model
    before issue 34 fails: its translation sigma covers under a fifth of the errors even at
    2 sigma (a tag's edges all sit inside their true lines, which shows in depth and in no
    residual)."""
    tr = tag_trials
    msg = _assert_covers("single tag", tr, mahalanobis_95=0.88)
    old_t2, _ = tr.coverage(2.0, old=True)
    assert old_t2 < 0.2, msg
    assert np.mean(tr.mahalanobis(old=True) <= CHI2_2S) < 0.2, msg


def test_small_field_sigma_covers_its_error(field_trials):
    """Issue 34 item 6 (small fields): over >= 200 renders of 6- and 9-corner ChArUco
    fields seen by one camera, each error component lies within 1 sigma in 55-85 % of
    poses and within 2 sigma in >= 90 %, and the 6-DOF Mahalanobis distance within
    chi-square's 95 % point in >= 90 %. No pose is in the mirror minimum of the planar
    ambiguity (over 10 deg off): the other IPPE pose is tried and kept where it fits
    better. Before issue 34 some were, each with a covariance that put the truth beyond
    chi-square's 99.9 % point."""
    tr = field_trials
    msg = _assert_covers("small field", tr, mahalanobis_95=0.90)
    assert tr.worst_rotation_deg() < 10.0, msg
    # before: mirrored poses, each reported as if sure (beyond chi-square's 99.9 % point)
    mirrored = np.degrees(np.linalg.norm(tr.old_errors[:, 3:], axis=1)) > 10.0
    assert np.any(mirrored), msg
    assert np.all(tr.mahalanobis(old=True)[mirrored] > chi2.ppf(0.999, 6)), msg


def _sigmas(cov: np.ndarray) -> tuple[float, float]:
    """Largest position (m) and rotation (deg) standard deviations, as PoseEstimate's."""
    pos = float(np.sqrt(np.max(np.linalg.eigvalsh(cov[:3, :3]))))
    return pos, float(np.degrees(np.sqrt(np.max(np.linalg.eigvalsh(cov[3:, 3:])))))


def test_wrong_tag_poses_trip_the_watchdog_and_the_body_gate(tag_trials):
    """Issue 34 item 6 (what the safety layer sees): every single-tag pose more than
    10 deg off reports a rotation sigma over the daemon's covariance watchdog limit
    ([safety] max_rotation_sigma_deg, 1 deg), so the watchdog trips on it, and every one
    more than 20 deg off (the mirror pose of a small, nearly face-on tag, which fits its
    corners as well as the truth) one over the tracker's body gate (5 deg), so it is
    withheld. Before issue 34 a pose 83 deg off reported 0.99 deg, and none of the mirror
    poses reached the body gate. Right poses (under 2 deg off) of the 100 px tags mostly
    pass the watchdog; those of the 72 px tags mostly trip its 1 mm position limit, as
    their true errors (median over 1 mm, mostly depth) would."""
    from oralnav.config.daemon import SafetySection
    from oralnav.control.vision.tracker import TrackerSettings

    tr = tag_trials
    gate = TrackerSettings().body_max_rotation_sigma_deg
    safety = SafetySection()
    rot_err = np.degrees(np.linalg.norm(tr.errors[:, 3:], axis=1))
    wrong, mirrored = np.nonzero(rot_err > 10.0)[0], np.nonzero(rot_err > 20.0)[0]
    assert len(mirrored) >= 1, "the grid must show the planar ambiguity"

    def trips(cov: np.ndarray) -> bool:
        dog = CovarianceWatchdog(safety.max_position_sigma, safety.max_rotation_sigma_deg)
        dog.pose("tag", *_sigmas(cov))
        return "rotation_sigma:tag" in [t.name for t in dog.check(0.0)]

    assert all(trips(tr.cov[i]) for i in wrong), rot_err[wrong]
    assert all(_sigmas(tr.cov[i])[1] > gate for i in mirrored), rot_err[mirrored]
    assert not all(trips(tr.old_cov[i]) for i in wrong)
    assert not any(_sigmas(tr.old_cov[i])[1] > gate for i in mirrored)
    # The tags' sizes: 32, 48, 72 and 100 px in blocks of 60 renders. Right poses of the
    # 100 px tags (30 mm at 0.18 m) mostly pass the watchdog; those of the 72 px tags
    # (0.25 m) mostly trip its 1 mm position limit, as their true errors would (mostly
    # depth: a tag's shared edge shift).
    size = np.array([s for s in TAG_SIDES_PX for _ in range(60)])[tr.kept]
    for side, expect_quiet in ((100.0, True), (72.0, False)):
        right = np.nonzero((size == side) & (rot_err < 2.0))[0]
        quiet = [not trips(tr.cov[i]) and _sigmas(tr.cov[i])[0] <= safety.max_position_sigma
                 for i in right]
        t_err = np.linalg.norm(tr.errors[right, :3], axis=1)
        assert len(right) >= 50
        if expect_quiet:
            assert np.mean(quiet) >= 0.6, np.mean(quiet)
        else:
            assert np.mean(quiet) < 0.5 and np.median(t_err) > safety.max_position_sigma


# -- the model's parts ----------------------------------------------------------------------
def test_pixel_variance_pools_the_residuals_with_the_prior():
    """Issue 34 item 6 (residual variance with the right degrees of freedom, combined with
    a prior): a 4-corner fit (2 residual degrees of freedom) with no residual still gets
    about the prior's variance; a 100-corner fit gets its own residual variance (within
    3 %), not the prior's; the result is never below MIN_SIGMA_PX squared."""
    noise = CornerNoise(sigma_px=0.2, dof=4)
    # 4 corners, a perfect fit: (4 * 0.04 + 0) / 6, times 6 / 4 for the Student-t
    assert pixel_variance(0.0, 8, noise) == pytest.approx(0.04)
    # a lucky 4-corner fit is pulled up toward the prior, a bad one stays bad
    assert pixel_variance(0.001, 8, noise) > 0.5 * noise.sigma_px ** 2
    assert pixel_variance(8.0, 8, noise) > 1.0
    # 100 corners at 0.5 px: the residuals decide
    s2 = pixel_variance(0.25 * 194, 200, noise)
    assert s2 == pytest.approx(0.25, rel=0.03)
    assert pixel_variance(0.0, 200, CornerNoise(sigma_px=0.0)) == MIN_SIGMA_PX ** 2


def _tag_observation(T_cam_tag: np.ndarray, body: RigidBody, shrink_px: float = 0.0,
                     sigma_px: float = 0.0, seed: int = 0) -> Observation:
    """Exact pixels of ``body``'s tag at ``T_cam_tag``, every edge moved ``shrink_px``
    into the tag, plus Gaussian noise."""
    px = CAMERA.project(body.corners() @ T_cam_tag[:3, :3].T + T_cam_tag[:3, 3])
    centre = px.mean(axis=0)
    if shrink_px:
        # along the bisector, sqrt(2) as far as each edge for a square seen face-on
        px = px - shrink_px * np.sqrt(2.0) * (px - centre) / np.linalg.norm(
            px - centre, axis=1, keepdims=True)
    px = px + np.random.default_rng(seed).normal(0.0, sigma_px, px.shape)
    return Observation(CAMERA, np.arange(4), px)


def test_a_shared_edge_shift_shows_in_depth_only_through_the_edge_term():
    """Issue 34 item 6 (correlated corner errors): a face-on 30 mm tag at 0.4 m whose four
    edges all sit 0.3 px inside their true lines (as blur leaves them) fits with no
    residual at a depth 3 mm too far. With the tag-corner model (shared edge shift,
    0.2 px) that error is within 2 sigma; with the same prior but no edge term it lies
    beyond 4 sigma, as it did before issue 34."""
    body = single_tag_body(0, 0.03, "DICT_4X4_50")
    T = make_transform(Rotation.from_euler("x", 5, degrees=True), [0.01, 0.0, 0.4])
    ob = _tag_observation(T, body, shrink_px=0.3)
    est = bundle_adjust(body_points(body), [ob], T, reject_outliers=False, noise=TAG_CORNERS)
    err = _error6(est.T_ref_field, T)
    assert est.reproj_rms_px < 0.01 and err[2] > 0.002, (est.reproj_rms_px, err)
    assert abs(err[2]) < 2.0 * np.sqrt(est.covariance[2, 2])
    no_edge = CornerNoise(TAG_CORNERS.sigma_px, TAG_CORNERS.dof)
    cov = pose_covariance(body_points(body), [ob], est.T_ref_field, no_edge)
    assert abs(err[2]) > 4.0 * np.sqrt(cov[2, 2])
    assert abs(err[2]) > 4.0 * np.sqrt(_old_covariance(body.corners(), ob,
                                                       est.T_ref_field)[2, 2])


def body_points(body: RigidBody):
    """``body`` as the corner model bundle adjustment reads (its corners, 4 per tag)."""

    class Points:
        corners = body.corners()

    return Points()


def test_planar_ambiguity_widens_the_covariance_and_keeps_the_better_pose():
    """Issue 34 item 6 (planar targets with few points): a small tag seen nearly face-on
    fits two poses, mirror images, almost equally (IPPE returns both). Started in the
    mirror pose, bundle adjustment returns the pose that fits better; the covariance
    then holds the mirror pose within chi-square's 95 % point, where the one-pose
    Gaussian put it hundreds of sigma away. A tilted, near tag has a mirror pose that
    fits far worse, and its covariance is the one-pose Gaussian."""
    import cv2

    body = single_tag_body(0, 0.03, "DICT_4X4_50")
    # 30 px across, turned 20 deg: mirror poses 39 deg apart fit to 0.057 and 0.069 px^2
    T = make_transform(Rotation.from_euler("xy", [20, 10], degrees=True), [0.02, 0.0, 0.6])
    ob = _tag_observation(T, body, sigma_px=0.15, seed=3)
    n, rvecs, tvecs, _ = cv2.solvePnPGeneric(body.corners(), ob.xy, np.eye(3), None,
                                             flags=cv2.SOLVEPNP_IPPE)
    poses = [make_transform(cv2.Rodrigues(r)[0], t.ravel()) for r, t in zip(rvecs, tvecs,
                                                                             strict=True)]
    ests = [bundle_adjust(body_points(body), [ob], P, reject_outliers=False,
                          noise=TAG_CORNERS) for P in poses]
    # both starts end in the same, better pose
    assert np.allclose(ests[0].T_ref_field, ests[1].T_ref_field, atol=1e-7)
    best = ests[0]
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pose_module, "_planar_ambiguity", lambda T, cov, *a: (T, cov))
        mirror = [bundle_adjust(body_points(body), [ob], P, reject_outliers=False,
                                noise=TAG_CORNERS) for P in poses]
    other = max(mirror, key=lambda e: np.linalg.norm(_error6(e.T_ref_field,
                                                             best.T_ref_field)[3:]))
    d = _error6(other.T_ref_field, best.T_ref_field)
    assert np.degrees(np.linalg.norm(d[3:])) > 30.0
    assert d @ np.linalg.solve(best.covariance, d) < CHI2_2S
    one_pose = min(mirror, key=lambda e: np.linalg.norm(_error6(e.T_ref_field,
                                                                best.T_ref_field)[3:]))
    assert d @ np.linalg.solve(one_pose.covariance, d) > 100.0
    # a near, tilted tag: the mirror pose fits far worse and adds nothing
    T = make_transform(Rotation.from_euler("xy", [35, 10], degrees=True), [0.0, 0.0, 0.2])
    ob = _tag_observation(T, body, sigma_px=0.15, seed=4)
    est = bundle_adjust(body_points(body), [ob], T, reject_outliers=False, noise=TAG_CORNERS)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pose_module, "_planar_ambiguity", lambda T, cov, *a: (T, cov))
        plain = bundle_adjust(body_points(body), [ob], T, reject_outliers=False,
                              noise=TAG_CORNERS)
    np.testing.assert_allclose(est.covariance, plain.covariance, rtol=1e-9, atol=1e-20)


def test_large_field_covariance_is_as_before():
    """Issue 34 item 6 (large ChArUco fields keep their accuracy): for the 10 x 7 plane and
    the 12 x 9 cylinder of the pose tests over both cameras and over one, with 0.05 and
    0.2 px of corner noise, the new covariance's standard deviations are within 2 % of
    the pre-issue-34 formula's (whose match to the Monte-Carlo spread
    tests/control/vision/test_pose.py checks)."""
    from pathlib import Path

    from oralnav.config.rig import load_rig
    from oralnav.control.geometry import transform_from_euler
    from oralnav.control.vision.markers import CylinderSurface

    rig = load_rig(Path(__file__).resolve().parents[3] / "config" / "rigs" / "stereo.toml")
    plane = MarkerField("plane", "DICT_4X4_1000", (10, 7), 0.004, 0.003)
    cylinder = MarkerField("cyl", "DICT_4X4_1000", (12, 9), 0.003, 0.0022, first_id=100,
                           surface=CylinderSurface(radius=0.010))
    cases = [(plane, transform_from_euler([-0.02, -0.015, 0.22], [10, -15, 5])),
             (cylinder, transform_from_euler([0.0, -0.012, 0.20], [5, 15, 10]))]
    rng = np.random.default_rng(34)
    for fld, T in cases:
        for cams in (rig.names, rig.names[:1]):
            for sigma in (0.05, 0.2):
                obs = []
                for name in cams:
                    cam = rig[name]
                    Tc = cam.T_cam_ref @ T
                    pc = fld.corners @ Tc[:3, :3].T + Tc[:3, 3]
                    facing = np.sum(fld.sheet_normals(fld.corners_flat) @ Tc[:3, :3].T
                                    * pc, axis=1) < 0
                    uv = cam.project(pc)
                    rows = np.nonzero(facing & cam.in_image(uv, margin=5))[0]
                    obs.append(Observation(cam, rows,
                                           uv[rows] + rng.normal(0, sigma, (len(rows), 2))))
                est = bundle_adjust(fld, obs, T)
                assert est is not None and est.corners >= 50
                old = np.zeros((6, 6))
                if len(obs) == 1:
                    old = _old_covariance(fld.corners, obs[0], est.T_ref_field)
                else:
                    X, xy, _, R_cr, t_cr, f = _stack(fld, obs)
                    r, J, _ = _residuals(est.T_ref_field, X, xy, R_cr, t_cr, f, True)
                    old = max(float(r @ r) / (len(r) - 6), MIN_SIGMA_PX ** 2) * np.linalg.inv(
                        J.T @ J)
                ratio = np.sqrt(np.diag(est.covariance) / np.diag(old))
                assert np.all(np.abs(ratio - 1.0) < 0.02), (fld.name, cams, sigma, ratio)
    assert FIELD_CORNERS.edge_sigma_px == 0 and not FIELD_CORNERS.tags


# -- real data ------------------------------------------------------------------------------
@needs_aruco_data
def test_peer_tag_video_sigma_against_its_spread():
    """Issue 34 item 6 (real data): the peer's output.avi (one 50 mm tag at 210 mm, 10
    frames, hand-held: no static repeats). Its frame-to-frame scatter about a smooth
    (cubic) track is at most the reported rotation sigma on every axis, and at most twice
    the reported position sigma (measured 2026-11-27: 0.44, 0.40, 0.09 deg against
    1.33, 1.29, 0.21 deg; 0.20, 0.24, 0.39 mm against 0.13, 0.17, 1.02 mm); the peer's
    regression pose of frame 1 lies within chi-square's 95 % point of ours."""
    from oralnav.config.rigid_bodies import load_calibration_txt
    from oralnav.control.vision.rigid_body import T_TAG_OPENCV_MARKER
    from oralnav.drivers.camera.replay import read_frame
    from tests.helpers import PEER_TAG0_MM, mm_to_m

    video = ARUCO_DATA / "output.avi"
    first = read_frame(video, 0)
    cam = load_calibration_txt(ARUCO_DATA / "calibration.txt", first.shape[::-1], name="cam")
    rig = Rig("cam", {"cam": cam})
    body = single_tag_body(0, 0.050, "DICT_4X4_50")
    poses, covs = [], []
    for k in range(10):
        tags = detect_tags(read_frame(video, k), "DICT_4X4_50")
        est = estimate_body(body, {"cam": tags}, rig)
        poses.append(est.T_ref_field)
        covs.append(est.covariance)
    R0 = poses[0][:3, :3]
    track = np.array([np.concatenate([T[:3, 3], Rotation.from_matrix(
        T[:3, :3] @ R0.T).as_rotvec()]) for T in poses])
    t = np.arange(10.0)
    fit = np.stack([np.polyval(np.polyfit(t, track[:, j], 3), t) for j in range(6)], axis=1)
    scatter = np.sqrt(np.sum((track - fit) ** 2, axis=0) / (10 - 4))
    reported = np.sqrt(np.mean([np.diag(c) for c in covs], axis=0))
    assert np.all(scatter[3:] <= reported[3:]), (np.degrees(scatter[3:]),
                                                 np.degrees(reported[3:]))
    assert np.all(scatter[:3] <= 2.0 * reported[:3]), (scatter[:3], reported[:3])
    e = _error6(mm_to_m(PEER_TAG0_MM) @ T_TAG_OPENCV_MARKER, poses[1])
    assert e @ np.linalg.solve(covs[1], e) < CHI2_2S
