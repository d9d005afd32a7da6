"""The visually guided needle procedure of seed 002 (§III, §IV.B): needle grasp (NG),
hand-off (NH), drive (ND), regrasp (NR) and pull (NP), driven through a needle cell.

Every step looks before it moves: the needle's pose comes from the tracker
(:class:`~oralnav.control.needle.tracker.NeedleTracker`) on the cell's stereo images, the
grippers' poses from the arms (what the robot reports; the simulated cell adds its fixed
kinematic error). A step that cannot be done safely refuses before any motion toward the
needle, with the reason (:attr:`StepResult.refused`): an undefined suture (``h > r``), a
needle or suture no arm reaches, a tracker that has not converged. A step that moved and
then saw something go wrong (a grasp whose needle does not follow the jaws, an arm that
stopped on its reach limit) fails with its cause. A step's own verdict is what it saw;
where the caller knows the truth (the simulator), it passes a check of each step against
it (``truth_check``, filling :attr:`StepResult.truth_ok`), which is what the Monte Carlo
bench counts; the procedure itself never reads the truth.

The steps (docs/needle.md, "Procedure"):

- **NG**: plan the suture (tissue frame from the incision, eqs. 2-4) and choose the
  driving arm and its grasp first (:func:`~oralnav.control.needle.grasp.select_grasp`
  with the arm's reach), so that the other arm picks the needle up far enough along the
  arc from where the driver will take it; approach along the gripper axis, reach, close
  (Fig. 5), lift, and check that the needle rose with the jaws.
- **NH**: carry the needle to a hand-off pose above the suture's start, chosen so both
  arms reach their grasps and both cameras see the needle; the driver takes it with its
  driving grasp at the *tracked* pose, the first arm opens and goes back to its park pose
  (Fig. 6); the driver lifts and checks that it holds.
- **ND**: the grasp the hand-off actually produced, seen by the tracker, is checked and
  the drive planned on it (eq. 3); approach, look again, then turn the needle about its
  centre from the entry to past the exit. From there on the tracker is told the tissue's
  surface (a plane through the incision), which hides the needle's middle. The tracked
  tip must end within ``placement_tolerance`` of the plan: checked here when the tracker
  converges with the jaws still on the needle, else by NR once they have backed off.
- **NR**: release, back off, track the needle standing in the tissue, grasp the tip part
  that stands out of the exit.
- **NP**: turn the needle further along its own arc until the swage is out, then lift.

Frames: the cell's reference frame (the endoscope's left channel, ``ref``) for
everything; the robot base P is ``ref`` here (the cell reports and takes gripper poses in
it, so ``G_PC`` is the identity). Metres and radians.

Not thread-safe: one caller at a time (the daemon runs steps in a worker thread under a
lock).

The modules: :mod:`.settings` (:class:`ProcedureSettings`), :mod:`.results` (the steps'
order, :class:`StepResult`, :class:`StepFailed`, :func:`step_rates`), :mod:`.cell` (what
the procedure needs of a cell), :mod:`.poses` (pose and path helpers), :mod:`.views`
(:class:`ViewRule` and the poses the needle is shown from), :mod:`.planning` (the plan's
geometry: drives, grasps, hand-off poses, the regrasp's tip part), :mod:`.ports` (entry
port selection), :mod:`.actions` (looking, moving, checking a hold) and :mod:`.steps`
(:class:`NeedleProcedure`).
"""

from oralnav.control.needle.procedure.cell import NeedleCellPort
from oralnav.control.needle.procedure.planning import drive_pick, drive_ways, tip_part
from oralnav.control.needle.procedure.ports import port_drives, port_pair
from oralnav.control.needle.procedure.poses import back_off, translation, turn_about
from oralnav.control.needle.procedure.results import STEPS, StepFailed, StepResult, step_rates
from oralnav.control.needle.procedure.settings import ProcedureSettings
from oralnav.control.needle.procedure.steps import NeedleProcedure, StepCheck
from oralnav.control.needle.procedure.views import ViewRule

__all__ = ["STEPS", "NeedleCellPort", "NeedleProcedure", "ProcedureSettings", "StepCheck",
           "StepFailed", "StepResult", "ViewRule", "back_off", "drive_pick", "drive_ways",
           "port_drives", "port_pair", "step_rates", "tip_part", "translation", "turn_about"]
