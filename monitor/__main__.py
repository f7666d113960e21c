import sys

from monitor.app.cli import program

sys.exit(program())
