"""A busy loop on every core (or N), for running tests and benchmarks under load.

python tools/cpuhog.py [N] -- COMMAND ...   run COMMAND while N busy loops spin
python tools/cpuhog.py [N]                  spin until Ctrl-C
"""

from __future__ import annotations

import multiprocessing as mp
import os
import subprocess
import sys


def spin(parent: int) -> None:
    """Spin until killed; die with the parent (even a SIGKILLed one: no orphaned hog)."""
    if sys.platform == "linux":
        import ctypes
        import signal

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        if os.getppid() != parent:  # the parent died before the death signal was set
            return
    while True:
        pass


def main(argv: list[str]) -> int:
    n = os.cpu_count() or 1
    if argv and argv[0].isdigit():
        n, argv = int(argv[0]), argv[1:]
    if argv and argv[0] == "--":
        argv = argv[1:]
    hogs = [mp.Process(target=spin, args=(os.getpid(),), daemon=True) for _ in range(n)]
    for h in hogs:
        h.start()
    try:
        if argv:
            return subprocess.call(argv)
        for h in hogs:
            h.join()
        return 0
    except KeyboardInterrupt:
        return 130
    finally:
        for h in hogs:
            h.kill()


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
