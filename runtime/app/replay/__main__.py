"""`python -m runtime.app.replay RECORDING ...`: `dct replay` where the `dct` entry points are not
(re)installed yet."""
from runtime.app.replay.cli import replay_command

replay_command(prog_name="dct replay")
