"""``python -m esa_server ARGS``: runs the installed ``esa-server`` with ARGS."""

import os
import sys

from esa_server import find_esa_server_bin

if __name__ == "__main__":
    binary = os.fsdecode(find_esa_server_bin())
    # exec: signals, the exit status and --parent-pid all concern the server itself.
    os.execv(binary, [binary, *sys.argv[1:]])
