"""`secure init --force` over a profile is all or nothing: a rename that fails, or a process killed at a rename,
leaves the old profile whole or the new one whole, never a mix of the two (a new CA with old keys). A fresh
profile written into an existing empty directory likewise leaves nothing of itself when a rename fails.

Faults are injected at ``os.rename`` / ``os.replace`` (the N-th call of the two, counted together, fails as a
full disk would, or kills the process with a real SIGKILL) and, once, at ``shutil.rmtree``; everything else is
real files.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from cryptography import x509

from orchestrator.secure import ROLES, SecureInitConfig, init_secure, planned_files
from orchestrator.transport import validate_secure_config
from tests.conftest import REPO, run_cli

ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _files(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


@contextmanager
def _rename_fails_at(monkeypatch: pytest.MonkeyPatch, *calls: int) -> Iterator[list[int]]:
    """The ``calls``-th ``os.rename`` / ``os.replace`` (counted together, from 1) fail with ENOSPC; the others are
    real. Yields the running count."""
    count = [0]
    real = {name: getattr(os, name) for name in ("rename", "replace")}

    def faulty(name: str):
        def call(src, dst, *args, **kwargs):
            count[0] += 1
            if count[0] in calls:
                raise OSError(errno.ENOSPC, "No space left on device", str(src))
            return real[name](src, dst, *args, **kwargs)
        return call

    with monkeypatch.context() as m:
        for name in real:
            m.setattr(os, name, faulty(name))
        yield count


def _assert_whole_new_profile(directory: Path, old: dict[str, bytes]) -> None:
    """Every planned file is there and none is the old one's; every certificate is signed by the CA there."""
    new = _files(directory)
    assert sorted(new) == sorted(old)
    assert [name for name in new if new[name] == old[name]] == []
    ca = x509.load_pem_x509_certificate(new["ca.pem"])
    for role in ROLES:
        x509.load_pem_x509_certificate(new[f"{role}.pem"]).verify_directly_issued_by(ca)
    assert validate_secure_config(directory / "worker.json5")


def test_a_rename_that_fails_anywhere_in_a_forced_init_leaves_the_old_profile_whole(monkeypatch, tmp_path):
    """Each rename the replacement makes fails in turn (until one run makes none fail): the old profile stays,
    byte for byte, and nothing else is left behind."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old = _files(directory)
    for call in range(1, 64):
        with _rename_fails_at(monkeypatch, call) as count:
            try:
                init_secure(SecureInitConfig(directory, force=True))
            except OSError as exc:
                assert "No space left on device" in str(exc)
                assert _files(directory) == old, f"rename {call} failed: old and new files mixed"
                assert sorted(p.name for p in tmp_path.iterdir()) == ["profile"], call  # no temporary folder
                continue
        assert count[0] < call  # a run with no failed rename: done
        break
    _assert_whole_new_profile(directory, old)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["profile"]  # the old one deleted once replaced


def test_when_the_old_profile_cannot_be_put_back_the_error_says_where_it_is(monkeypatch, tmp_path, capsys):
    """The new folder cannot be renamed into place and the old one cannot be renamed back: the old profile is
    whole, aside, and the one-line error names it."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old = _files(directory)
    with _rename_fails_at(monkeypatch, 2, 3):
        rc, out, err = run_cli(capsys, "secure", "init", str(directory), "--force")
    lines = err.strip().splitlines()
    assert rc == 1 and not out and len(lines) == 1, (rc, out, err)
    [aside] = [p for p in tmp_path.iterdir() if p.name.startswith(".profile.old-")]
    assert not directory.exists() and _files(aside) == old
    assert str(aside) in lines[0] and "rename it back" in lines[0], lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == [aside.name]  # the new one not left lying about


def test_an_old_profile_that_cannot_be_deleted_is_named_in_a_warning(monkeypatch, tmp_path, capsys):
    """The new profile is in place (exit 0); the old one, which holds the old keys, is whole and named."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old = _files(directory)
    real_rmtree = shutil.rmtree

    def rmtree(path, *args, **kwargs):
        if Path(path).name.startswith(".profile.old-"):
            raise OSError(errno.EACCES, "Permission denied", str(path))
        return real_rmtree(path, *args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(shutil, "rmtree", rmtree)
        rc, out, err = run_cli(capsys, "secure", "init", str(directory), "--force", "--json")
    [aside] = [p for p in tmp_path.iterdir() if p.name.startswith(".profile.old-")]
    assert rc == 0 and json.loads(out)["left_over"] == str(aside) and _files(aside) == old
    assert "warning" in err and str(aside) in err and len(err.strip().splitlines()) == 1, err
    _assert_whole_new_profile(directory, old)


KILLED_AT_RENAME = """
import os, signal, sys
from orchestrator.secure import SecureInitConfig, init_secure

calls, kill_at = [0], int(sys.argv[2])
def killing(real):
    def call(*args, **kwargs):
        calls[0] += 1
        if calls[0] == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
        return real(*args, **kwargs)
    return call
os.rename, os.replace = killing(os.rename), killing(os.replace)
init_secure(SecureInitConfig(sys.argv[1], force=True))
"""


@pytest.mark.parametrize("kill_at", [1, 2, 3])
def test_a_forced_init_killed_at_a_rename_leaves_one_whole_profile(tmp_path, kill_at):
    """After a real SIGKILL at the ``kill_at``-th rename: the directory holds the old profile or the new one,
    whole; or (killed between the two renames) the old one is whole, aside."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old = _files(directory)
    done = subprocess.run([sys.executable, "-c", KILLED_AT_RENAME, str(directory), str(kill_at)], cwd=REPO,
                          capture_output=True, text=True, timeout=120, env=ENV)
    assert done.returncode in (0, -signal.SIGKILL), done.stderr
    if not directory.exists():
        [aside] = [p for p in tmp_path.iterdir() if p.name.startswith(".profile.old-")]
        assert _files(aside) == old
    elif _files(directory) != old:
        _assert_whole_new_profile(directory, old)


def test_a_failed_rename_into_an_existing_empty_directory_leaves_it_empty(monkeypatch, tmp_path):
    directory = tmp_path / "profile"
    directory.mkdir()
    with _rename_fails_at(monkeypatch, 4), pytest.raises(OSError, match="No space left on device"):
        init_secure(SecureInitConfig(directory))
    assert directory.is_dir() and list(directory.iterdir()) == []  # no half profile that --force would need
    first = init_secure(SecureInitConfig(directory))  # and a plain init works there again
    assert sorted(p.name for p in directory.iterdir()) == sorted(p.name for p in planned_files(directory))
    assert first.configs["worker"].is_file()


def test_a_forced_init_through_a_link_replaces_the_profile_where_it_points(tmp_path):
    """The configs name the files by their resolved paths: those are the ones replaced; the link stays."""
    real, link = tmp_path / "real-profile", tmp_path / "profile"
    init_secure(SecureInitConfig(real))
    link.symlink_to(real, target_is_directory=True)
    old = _files(real)
    second = init_secure(SecureInitConfig(link, force=True))
    assert link.is_symlink() and link.resolve() == real.resolve()
    _assert_whole_new_profile(real, old)
    named = validate_secure_config(second.configs["worker"])
    assert all(p.resolve().parent == real.resolve() for p in map(Path, named))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["profile", "real-profile"]
