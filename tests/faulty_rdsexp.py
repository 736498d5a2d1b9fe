"""`python tests/faulty_rdsexp.py FAULT ARGS...`: run `rdsexp ARGS` with an injected file-system
fault (for tests/experiment/test_store.py; the checks run as root too, where file modes stop nothing).

FAULT is
- `erofs:DIR`: every write under DIR fails as on a read-only file system (EROFS);
- `kill:NAME`: the process is killed (SIGKILL) while writing a file named NAME, after its bytes are
  written to the temporary file and before the rename.
"""
import builtins
import errno
import io
import os
import signal
import sys

fault, arg = sys.argv[1].split(":", 1)
if fault == "erofs":
    root = os.path.realpath(arg)

    def under(path) -> bool:
        return not isinstance(path, int) and os.path.realpath(os.fspath(path)).startswith(root)

    def deny(path):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), os.fspath(path))

    _open = builtins.open

    def patched_open(file, mode="r", *args, **kwargs):
        if any(c in mode for c in "wax+") and under(file):
            deny(file)
        return _open(file, mode, *args, **kwargs)

    builtins.open = io.open = patched_open
    _mkdir = os.mkdir

    def patched_mkdir(path, *args, **kwargs):
        if under(path):
            deny(path)
        return _mkdir(path, *args, **kwargs)

    os.mkdir = patched_mkdir

    def guarded(call):
        def patched(src, dst, *args, **kwargs):
            if under(dst):
                deny(dst)
            return call(src, dst, *args, **kwargs)
        return patched

    for name in ("replace", "rename", "link"):
        setattr(os, name, guarded(getattr(os, name)))
elif fault == "kill":
    _fsync = os.fsync

    def patched_fsync(fd):
        if os.path.basename(os.readlink(f"/proc/self/fd/{fd}")).startswith(f".{arg}."):
            os.kill(os.getpid(), signal.SIGKILL)
        return _fsync(fd)

    os.fsync = patched_fsync
else:
    sys.exit(f"unknown fault {fault!r}")

sys.argv = ["rdsexp", *sys.argv[2:]]
from rdsexp.experiment.cli import main  # noqa: E402

main()
