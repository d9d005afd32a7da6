"""``python -m oralnav.sim.peers.ur [--host H] [--series e|cb3] [--dashboard-port P]``: a
fake UR controller until Ctrl-C (also the child of ``FakeURControllerProcess``, ``--rpc``)."""

from oralnav.sim.peers.ur.process import main

if __name__ == "__main__":
    main()
