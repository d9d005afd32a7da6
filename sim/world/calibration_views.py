"""Simulated camera-calibration sessions: a ChArUco board shown to a rig in many poses.

For a rig (or one camera of it) and a flat ChArUco board, :func:`board_poses` draws a
seeded, deterministic set of board poses that together cover each camera's image, at a
range of working distances and tilted 15-45 deg about varied in-plane axes;
:func:`render_calibration_views` renders them through
:class:`~oralnav.sim.world.render.SceneRenderer`
with a realistic imaging model and finds the board's chessboard corners with the project's
detector (:func:`oralnav.control.vision.detection.detect_fields`). What comes back is what a real
calibration session yields, the detected corners of every image, plus the truth: every
view's board pose and exact corner pixels.

Frames and units: ``T_ref_board`` is the board's pose in the rig's reference frame,
``T_cam_board`` in one camera's frame (metres). The board frame is the field frame of
:mod:`oralnav.control.vision.markers` (origin at the board's outer corner, z away from the camera
that sees the printed face).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.geometry import invert, make_transform
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.detection import FieldCorners, QuadParams, detect_fields
from oralnav.control.vision.markers import MarkerField, PlaneSurface
from oralnav.sim.world.render import FieldTruth, RenderError, SceneRenderer
from oralnav.sim.world.scene import Imaging, Placement, Scene

__all__ = [
    "CALIBRATION_IMAGING",
    "CalibrationViews",
    "board_poses",
    "default_board",
    "default_distances",
    "render_calibration_views",
]

#: Imaging of a calibration session: a sharp lens with a slight point-spread function,
#: some read and shot noise, a mild illumination gradient.
CALIBRATION_IMAGING = Imaging(supersample=2, background=60.0, white=215.0, black=25.0,
                              illumination_gradient=(0.1, -0.08), blur_sigma_px=0.9,
                              read_noise_dn=1.5, shot_noise_gain=0.05)

#: Placement name of the board in the scenes built here.
BOARD = "board"


def default_board(kind: str = "stereo") -> MarkerField:
    """A flat ChArUco calibration board (DICT_4X4_1000, ids from 0).

    ``kind`` ``"stereo"``: 12 x 9 squares of 20 mm (240 x 180 mm), for the stereo pair at
    about 0.45-0.75 m. ``"endoscope"``: 16 x 12 squares of 2 mm (32 x 24 mm), for the
    endoscope's short working distance (about 25-45 mm); more, smaller squares put corners
    closer to the image corners, where a strong-distortion model is otherwise extrapolated.

    Markers are 0.6 of a square, leaving 0.2 square of plain print round each corner. With
    the usual 0.75 the detector's subpixel window (0.13 of the mean square side) reaches
    the markers on the foreshortened side of a corner on boards tilted 30-45 deg, and the
    pull biases the focal length by about +0.02 % (measured on the simulated endoscope:
    +0.012 to +0.023 % over five seeds with 0.75, within +-0.006 % with 0.6).
    """
    layouts = {"stereo": ((12, 9), 0.020), "endoscope": ((16, 12), 0.002)}
    if kind not in layouts:
        raise ValueError(f"default_board: kind must be one of {sorted(layouts)}, got {kind!r}")
    squares, s = layouts[kind]
    return MarkerField(f"calib_{kind}", "DICT_4X4_1000", squares, s, 0.6 * s)


def default_distances(board: MarkerField, camera: CameraModel) -> tuple[float, float]:
    """Working distances (m, along the optical axis) at which ``board`` spans about 70 % to
    40 % of ``camera``'s image width: near enough for accurate corners, far enough that
    one view does not fill the image."""
    width = board.sheet_size[0]
    f = camera.K[0, 0]
    return (f * width / (0.70 * camera.width), f * width / (0.40 * camera.width))


def _stratified(n: int, cells: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """``n`` points in the unit square (n x 2), one per cell of a ``cells`` grid in a
    shuffled order (again and again when n exceeds the cell count), jittered in the cell."""
    gx, gy = cells
    out = []
    while len(out) < n:
        order = rng.permutation(gx * gy)
        for c in order:
            out.append(((c % gx + rng.uniform()) / gx, (c // gx + rng.uniform()) / gy))
    return np.asarray(out[:n], dtype=float).reshape(-1, 2)


def board_poses(rig: Rig, board: MarkerField, n: int, *,
                cameras: Sequence[str] | None = None,
                distance: tuple[float, float] | None = None,
                tilt_deg: tuple[float, float] = (15.0, 45.0),
                spin_deg: float = 30.0, centre_span: float = 0.84,
                cells: tuple[int, int] = (3, 3), seed: int = 0) -> list[np.ndarray]:
    """``n`` board poses ``T_ref_board`` (4 x 4, m) covering the cameras' images.

    View ``k`` is aimed at camera ``cameras[k % len(cameras)]`` (default: every camera of
    the rig). The board's centre lies on the viewing ray of a target pixel, at a depth
    (along the optical axis) drawn from ``distance`` (m; default
    :func:`default_distances`); the board first faces that ray squarely, then turns by a
    tilt drawn from ``tilt_deg`` about an in-plane axis, and spins by up to ``spin_deg``
    about its normal. Deterministic for a given ``seed``.

    - A camera's first four views target its image's four corners, so that the board
      hangs off two edges and its corners reach into the image corner, where a distortion
      model would otherwise be extrapolated. These boards sit in the far half of the
      working range and tilt by the lower half of ``tilt_deg`` about the image's radial
      direction: the foreshortening then runs along the image edge, not along the radial
      direction that a barrel distortion already compresses, and the markers stay
      readable.
    - The other views target pixels drawn, stratified over a ``cells`` grid, from the
      central ``centre_span`` of the image; their tilt axes step by the golden angle from
      view to view, so they spread evenly round the normal.
    """
    if not isinstance(board.surface, PlaneSurface):
        raise RenderError(f"board {board.name!r}: a calibration board must be flat")
    if n < 1:
        raise RenderError(f"board_poses: n must be at least 1, got {n}")
    names = tuple(cameras) if cameras is not None else tuple(rig.names)
    cams = [rig[c] for c in names]  # raises on an unknown name
    lo_t, hi_t = tilt_deg
    if not 0.0 <= lo_t <= hi_t < 80.0:
        raise RenderError(f"board_poses: tilt_deg must satisfy 0 <= low <= high < 80, "
                          f"got {tilt_deg}")
    if distance is not None and not 0.0 < distance[0] <= distance[1]:
        raise RenderError(f"board_poses: distance must be (near, far) with 0 < near <= far, "
                          f"got {distance}")
    rng = np.random.default_rng(seed)
    targets = {}
    m = -(-n // len(cams))
    for c in cams:
        corners = np.array([(0.0, 0.0), (1.0, 1.0), (1.0, 0.0), (0.0, 1.0)])[:m]
        inner = 0.5 + (_stratified(m - len(corners), cells, rng) - 0.5) * centre_span
        targets[c.name] = np.concatenate([corners, inner])
    centre_b = np.array([0.5 * board.sheet_size[0], 0.5 * board.sheet_size[1], 0.0])
    golden = np.pi * (3.0 - np.sqrt(5.0))
    phase = rng.uniform(0.0, 2.0 * np.pi)
    out = []
    for k in range(n):
        cam = cams[k % len(cams)]
        j = k // len(cams)  # this camera's view number
        uv = targets[cam.name][j] * (np.array(cam.size) - 1.0)
        near, far = distance if distance is not None else default_distances(board, cam)
        ray = cam.backproject(uv[None])[0]
        # Face the ray squarely: board z along the ray (away from the camera), board x as
        # close to the camera's x as that allows (so face x, y run about as image x, y).
        z = ray / np.linalg.norm(ray)
        x = np.array([1.0, 0.0, 0.0]) - z[0] * z
        x /= np.linalg.norm(x)
        face = np.column_stack([x, np.cross(z, x), z])
        if j < 4:
            depth = rng.uniform(0.5 * (near + far), far)
            radial = uv - cam.K[:2, 2]
            psi = np.arctan2(radial[1], radial[0]) + np.radians(rng.uniform(-10.0, 10.0))
            tilt = np.radians(rng.uniform(lo_t, 0.5 * (lo_t + hi_t)))
        else:
            depth = rng.uniform(near, far)
            psi = phase + k * golden
            tilt = np.radians(rng.uniform(lo_t, hi_t))
        spin = np.radians(rng.uniform(-spin_deg, spin_deg))
        R = (Rotation.from_matrix(face)
             * Rotation.from_rotvec(tilt * np.array([np.cos(psi), np.sin(psi), 0.0]))
             * Rotation.from_rotvec([0.0, 0.0, spin]))
        T_cam_board = make_transform(R, ray * depth / ray[2] - R.apply(centre_b))
        out.append(cam.T_ref_cam @ T_cam_board)
    return out


@dataclass(frozen=True, eq=False)
class CalibrationViews:
    """A rendered calibration session.

    Attributes:
        rig: the rig the views were rendered through (its true calibration).
        board: the board shown.
        T_ref_board: board pose in the rig's reference frame per view (V x 4 x 4, m).
        views: per camera, the detected corners of each view (``None`` where the detector
            found none); index ``k`` of every camera is the same instant.
        truth: per camera, each view's ground truth (``None`` where no corner is visible).
        render_s: time spent rendering and detecting (s).
    """

    rig: Rig
    board: MarkerField
    T_ref_board: tuple[np.ndarray, ...]
    views: Mapping[str, tuple[FieldCorners | None, ...]]
    truth: Mapping[str, tuple[FieldTruth | None, ...]]
    render_s: float = 0.0

    def __len__(self) -> int:
        return len(self.T_ref_board)

    @property
    def cameras(self) -> tuple[str, ...]:
        return tuple(self.views)

    def T_cam_board(self, camera: str) -> list[np.ndarray]:
        """True board pose in ``camera``'s frame per view (4 x 4, m)."""
        T_cam_ref = invert(self.rig[camera].T_ref_cam)
        return [T_cam_ref @ T for T in self.T_ref_board]


def render_calibration_views(rig: Rig | CameraModel, board: MarkerField | None = None,
                             n: int = 20, *, cameras: Sequence[str] | None = None,
                             poses: Sequence[np.ndarray] | None = None,
                             distance: tuple[float, float] | None = None,
                             tilt_deg: tuple[float, float] = (15.0, 45.0),
                             imaging: Imaging = CALIBRATION_IMAGING,
                             quad_params: QuadParams | None = None, seed: int = 0,
                             progress: Callable[[int, int], None] | None = None,
                             on_frame: Callable[[int, Mapping[str, np.ndarray]], None]
                             | None = None) -> CalibrationViews:
    """Render ``n`` views of ``board`` through ``rig`` and detect its corners in each.

    ``rig`` may be a single :class:`CameraModel` (a one-camera rig is built around it).
    ``cameras`` restricts the cameras rendered (default all). ``poses`` (V x 4 x 4,
    ``T_ref_board``, m) replaces the generated poses (then ``n`` is ignored); otherwise
    :func:`board_poses` draws them with ``distance``, ``tilt_deg`` and ``seed``.
    ``board`` defaults to :func:`default_board`: ``"endoscope"`` when the first camera
    rendered is wide-angle (a horizontal field of view over 60 deg), else ``"stereo"``.
    The image noise of view ``k`` is the renderer's draw ``k`` for ``seed``.
    ``progress(done, total)`` is called after each view, ``on_frame(k, images)`` with each
    view's images (camera -> mono8), e.g. to save them. Cost on one core, 1920 x 1200:
    about 2.5 s per camera once (its ray map), then about 0.07 s per camera and view
    (render and detect, supersample 2).
    """
    if isinstance(rig, CameraModel):
        rig = Rig(rig.name, {rig.name: replace(rig, T_ref_cam=np.eye(4))})
    names = tuple(cameras) if cameras is not None else tuple(rig.names)
    for c in names:
        rig[c]  # noqa: B018 - raises on an unknown camera
    if board is None:
        first = rig[names[0]]
        hfov = 2.0 * np.arctan(0.5 * first.width / first.K[0, 0])
        board = default_board("endoscope" if hfov > np.radians(60.0) else "stereo")
    if poses is None:
        poses = board_poses(rig, board, n, cameras=names, distance=distance,
                            tilt_deg=tilt_deg, seed=seed)
    poses = tuple(np.asarray(T, dtype=float) for T in poses)
    scene = Scene(rig=rig, placements=(Placement(BOARD, board, poses[0] if poses
                                                 else np.eye(4)),),
                  imaging=imaging, seed=seed)
    renderer = SceneRenderer(scene)
    t0 = time.perf_counter()
    views: dict[str, list[FieldCorners | None]] = {c: [] for c in names}
    truth: dict[str, list[FieldTruth | None]] = {c: [] for c in names}
    for k, T in enumerate(poses):
        frame = renderer.render(poses={BOARD: T}, frame=k, cameras=names)
        if on_frame is not None:
            on_frame(k, frame.images)
        for c in names:
            found = detect_fields(frame.images[c], [board], quad_params or QuadParams())
            views[c].append(found.get(board.name))
            truth[c].append(frame.truth[c].get(BOARD))
        if progress is not None:
            progress(k + 1, len(poses))
    return CalibrationViews(rig=rig, board=board, T_ref_board=poses,
                            views={c: tuple(v) for c, v in views.items()},
                            truth={c: tuple(v) for c, v in truth.items()},
                            render_s=time.perf_counter() - t0)
