"""The hardware-in-the-loop cell: the simulated world seen through protocol peers.

The world (``sim/world``) and the protocol peers (``sim/peers``) stay independent; this
package joins them: the cell's renderer draws what the fake UR controller and the drive
unit actually do, and streams it through simulated GigE cameras (``cameras.py``), and a
loopback service reports the ground truth of each capture (``truth.py``).
"""
