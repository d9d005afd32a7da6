"""ArUco rigid bodies filmed by one camera: the example recording of ``oralnav sim aruco``.

``oralnav track --calibration ... --body ... --tag ... --replay ...`` reads a camera
calibration, rigid-body tag tables and a video (the scikit-surgery formats). This module
makes all three from the scene renderer, with exact ground truth, so that command runs
on a fresh clone:

- ``reference``: 12 tags of ``DICT_ARUCO_ORIGINAL`` (ids 100-111, 13.5 mm) on a plate,
  posed as one rigid body;
- ``tag``: tag 0 of ``DICT_4X4_50``, 50 mm, tracked as a one-tag body
  (``--tag tag=DICT_4X4_50:0:50``).

The renderer draws ChArUco sheets, so each plate is a ChArUco sheet whose ArUco markers
are the body's tags (the chessboard squares between them are ignored by the body
tracker); the tag plate's second marker (``DICT_4X4_50`` id 1) is not tracked. Both
plates rock and drift a little from frame to frame in front of the camera, about 0.3 m
away.

Frames: the camera frame ``cam`` is the reference (OpenCV: x right, y down, z along the
optical axis); a plate's frame is its sheet's (origin at a sheet corner, x and y along
the print, z away from the camera that sees it). ``reference``'s body frame is its
plate's; ``tag``'s is the tag's centre with the plate's axes (the frame of
:func:`~oralnav.control.vision.rigid_body.single_tag_body`). Lengths in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.geometry import make_transform
from oralnav.control.vision.camera import CameraModel, Rig
from oralnav.control.vision.markers import MarkerField
from oralnav.control.vision.rigid_body import RigidBody
from oralnav.sim.world.render import SceneRenderer
from oralnav.sim.world.scene import Imaging, Placement, Scene

__all__ = ["CAMERA", "REFERENCE_PLATE", "TAG_ID", "TAG_PLATE", "TAG_SPEC", "TagVideo",
           "body_poses", "bodies", "field_body", "plate_poses", "render_tag_video"]

#: The camera: VGA, 600 px focal length (about 56 deg across), a little barrel distortion.
CAMERA = CameraModel("cam", (640, 480), np.array([[600.0, 0.0, 320.0],
                                                 [0.0, 600.0, 240.0],
                                                 [0.0, 0.0, 1.0]]),
                     np.array([-0.08, 0.05, 0.0, 0.0, 0.0]))
#: The reference body's plate: 6 x 4 squares of 18 mm, 12 markers of 13.5 mm (ids 100-111).
REFERENCE_PLATE = MarkerField(name="reference", dictionary="DICT_ARUCO_ORIGINAL",
                              squares=(6, 4), square=0.018, marker=0.0135, first_id=100)
#: The single tag's plate: 2 x 2 squares of 66 mm, markers 0 and 1 of 50 mm.
TAG_PLATE = MarkerField(name="tag", dictionary="DICT_4X4_50", squares=(2, 2),
                        square=0.066, marker=0.05, first_id=0)
#: The tracked tag on the tag plate, and ``oralnav track --tag``'s spelling of it.
TAG_ID = 0
TAG_SPEC = f"tag={TAG_PLATE.dictionary}:{TAG_ID}:{TAG_PLATE.marker * 1e3:g}"

# Where the plates stand, camera frame: centres (m) and tilts (deg, xyz Euler), chosen so
# that both stay whole in the image through their motion.
_CENTRES = {"reference": np.array([-0.072, 0.0, 0.30]), "tag": np.array([0.078, 0.0, 0.32])}
_TILTS = {"reference": (10.0, 20.0, 5.0), "tag": (-15.0, -10.0, -8.0)}
# The motion: each plate rocks by up to this many degrees and drifts by up to this many
# metres, with a period of this many frames (so even 3 frames differ).
_ROCK_DEG = 8.0
_DRIFT = 0.008
_PERIOD = 40


def field_body(fld: MarkerField, name: str | None = None) -> RigidBody:
    """The ArUco markers of a flat ChArUco sheet as a rigid body in the sheet's frame (m).

    The corners are OpenCV's board model, top-left, top-right, bottom-right, bottom-left
    of each marker as printed: the order the detector reports them in.
    """
    ids = fld.board.getIds()
    pts = fld.board.getObjPoints()
    # OpenCV keeps the model in float32: round its last bits (0.1 um) back to the design
    return RigidBody(name or fld.name, fld.dictionary,
                     {int(i): np.round(np.asarray(p, dtype=float).reshape(4, 3), 7)
                      for i, p in zip(ids, pts, strict=True)})


def _tag_offset() -> np.ndarray:
    """``T_plate_tag``: the tracked tag's centre on its plate, plate axes."""
    body = field_body(TAG_PLATE)
    return make_transform(None, body.tags[TAG_ID].mean(axis=0))


def plate_poses(frame: int) -> dict[str, np.ndarray]:
    """``T_cam_plate`` of each plate at ``frame`` (by plate name, m)."""
    out = {}
    for k, (name, centre) in enumerate(_CENTRES.items()):
        fld = REFERENCE_PLATE if name == "reference" else TAG_PLATE
        phase = 2.0 * np.pi * frame / _PERIOD + k * np.pi / 3
        rock = np.radians(_ROCK_DEG) * np.array([np.sin(phase), np.cos(1.3 * phase), 0.0])
        R = (Rotation.from_euler("xyz", _TILTS[name], degrees=True)
             * Rotation.from_rotvec(rock)).as_matrix()
        half = 0.5 * np.array([*fld.sheet_size, 0.0])
        drift = _DRIFT * np.array([np.cos(phase), np.sin(phase), 0.5 * np.sin(2 * phase)])
        # the sheet's origin is a corner: place the sheet's centre at the centre given
        out[name] = make_transform(R, centre + drift - R @ half)
    return out


def bodies() -> dict[str, RigidBody]:
    """The rigid bodies the recording shows, by name: ``reference`` (the reference plate's
    12 markers, plate frame) and ``tag`` (tag :data:`TAG_ID`, centred on its origin)."""
    T_plate_tag = _tag_offset()
    tag = RigidBody("tag", TAG_PLATE.dictionary,
                    {TAG_ID: field_body(TAG_PLATE).tags[TAG_ID] - T_plate_tag[:3, 3]})
    return {"reference": field_body(REFERENCE_PLATE), "tag": tag}


def body_poses(frame: int) -> dict[str, np.ndarray]:
    """``T_cam_body`` of each of :func:`bodies` at ``frame`` (m): the truth."""
    poses = plate_poses(frame)
    return {"reference": poses["reference"], "tag": poses["tag"] @ _tag_offset()}


@dataclass(frozen=True)
class TagVideo:
    """A rendered recording and what it shows.

    ``images``: mono8 frames; ``camera``: the camera that took them (its true
    calibration); ``bodies``: the rigid bodies by name, ``tag`` being the one-tag body;
    ``truth``: per frame, ``T_cam_body`` of each body (m).
    """

    images: list[np.ndarray]
    camera: CameraModel
    bodies: dict[str, RigidBody]
    truth: list[dict[str, np.ndarray]]


def render_tag_video(frames: int, seed: int = 0, progress=None) -> TagVideo:
    """Render ``frames`` frames of the two plates moving in front of :data:`CAMERA`.

    Imaging: 2x2 supersampling, 0.6 px optical blur, 1.5 DN read noise (seeded by
    ``seed`` and the frame). ``progress(k, n)`` is called after each frame when given.
    Raises ``ValueError`` for fewer than 1 frame.
    """
    if frames < 1:
        raise ValueError(f"frames must be at least 1, got {frames}")
    scene = Scene(rig=Rig(CAMERA.name, {CAMERA.name: CAMERA}),
                  placements=tuple(Placement(f.name, f, T) for f, T in zip(
                      (REFERENCE_PLATE, TAG_PLATE), plate_poses(0).values(), strict=True)),
                  imaging=Imaging(blur_sigma_px=0.6, read_noise_dn=1.5), seed=seed,
                  source="oralnav.sim.world.aruco_video")
    renderer = SceneRenderer(scene)
    images = []
    for k in range(frames):
        images.append(renderer.render(plate_poses(k), frame=k).images[CAMERA.name])
        if progress is not None:
            progress(k + 1, frames)
    return TagVideo(images=images, camera=CAMERA, bodies=bodies(),
                    truth=[body_poses(k) for k in range(frames)])
