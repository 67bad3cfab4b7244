"""`dct replay`: the controller run open loop on a recording of the robot's inputs (cli.py: the
command; source.py: reading recordings and bags; inject.py: the recorded inputs as a transport, a
CAN bus and a VLM stand-in; clock.py: the recording's ticks as the loop's clock; icp.py: ICP as the
live run did it; session.py: one replay; outputs.py: what it writes). docs/decisions/replay.md."""
