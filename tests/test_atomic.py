"""Atomic writes give the files they write the permissions a plain open() would."""

import os
import stat

from offline_rl_core.common.atomic import atomic_path, write_json_atomic


def test_atomically_written_files_get_the_mode_a_plain_open_gives(tmp_path):
    """policy.pt, metrics.json and the figures must be readable by whoever the umask lets
    read them (a policy node under another user), not 0600 whatever the umask."""
    for umask in (0o022, 0o027, 0o002):
        before = os.umask(umask)
        try:
            with open(tmp_path / f"plain_{umask:o}", "w"):
                pass
            write_json_atomic(tmp_path / f"metrics_{umask:o}.json", {"a": 1})
            with atomic_path(tmp_path / f"policy_{umask:o}.pt") as tmp:
                tmp.write_bytes(b"weights")
        finally:
            os.umask(before)
        plain = stat.S_IMODE((tmp_path / f"plain_{umask:o}").stat().st_mode)
        assert plain == 0o666 & ~umask
        for name in (f"metrics_{umask:o}.json", f"policy_{umask:o}.pt"):
            assert oct(stat.S_IMODE((tmp_path / name).stat().st_mode)) == oct(plain), name
