"""`secure init --force` over a profile is all or nothing: a rename that fails, or a process killed at a rename,
leaves the old profile whole or the new one whole, never a mix of the two (a new CA with old keys). A fresh
profile written into an existing empty directory likewise leaves nothing of itself when a rename fails.

Faults are injected at ``os.rename`` / ``os.replace`` (the N-th call of the two, counted together, fails as a
full disk would, or kills the process with a real SIGKILL) and, once, at ``shutil.rmtree``; everything else is
real files. Where the profile's folder cannot be renamed (a mount point: EBUSY, injected, and a real tmpfs mounted
in a mount namespace of the test's own where one can be made), the files are swapped inside it, all or nothing too.
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

from orchestrator.acl import ROLES
from orchestrator.secure import SecureInitConfig, init_secure, planned_files
from orchestrator.transport import SecureConfigError, validate_secure_config
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


@contextmanager
def _undeletable(monkeypatch: pytest.MonkeyPatch, prefix: str) -> Iterator[None]:
    """``shutil.rmtree`` of a folder whose name starts with ``prefix`` fails (EACCES); any other is real."""
    real = shutil.rmtree

    def rmtree(path, *args, **kwargs):
        if Path(path).name.startswith(prefix):
            raise OSError(errno.EACCES, "Permission denied", str(path))
        return real(path, *args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(shutil, "rmtree", rmtree)
        yield


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
    with _undeletable(monkeypatch, ".profile.old-"):
        rc, out, err = run_cli(capsys, "secure", "init", str(directory), "--force", "--json")
    [aside] = [p for p in tmp_path.iterdir() if p.name.startswith(".profile.old-")]
    assert rc == 0 and json.loads(out)["left_over"] == str(aside) and _files(aside) == old
    assert "warning" in err and str(aside) in err and len(err.strip().splitlines()) == 1, err
    _assert_whole_new_profile(directory, old)


KILLED_AT_RENAME = """
import errno, os, signal, sys
from pathlib import Path
from orchestrator.secure import SecureInitConfig, init_secure

calls, kill_at = [0], int(sys.argv[2])
busy = Path(sys.argv[1]).resolve() if sys.argv[3:] == ["busy"] else None  # renamed, as a mount point would be
def killing(real):
    def call(src, *args, **kwargs):
        calls[0] += 1
        if calls[0] == kill_at:
            os.kill(os.getpid(), signal.SIGKILL)
        if Path(src) == busy:
            raise OSError(errno.EBUSY, os.strerror(errno.EBUSY), str(src))
        return real(src, *args, **kwargs)
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
    # the next init names what the crash left beside the directory (keys, passwords); --force deletes it
    left = sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".profile."))
    if left:
        with pytest.raises(SecureConfigError, match="cut short") as info:
            init_secure(SecureInitConfig(directory))
        assert all(name in str(info.value) for name in left), info.value
        if not directory.exists():
            assert f"the old profile is whole in {aside}" in str(info.value)
    init_secure(SecureInitConfig(directory, force=True))
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".profile.")]
    _assert_whole_new_profile(directory, old)


def test_a_first_init_killed_midway_is_finished_by_force(tmp_path):
    """Killed while placing its files: some in place, the rest staged as ``.NAME.tmp``. Those are its own, not
    "other files" that made every init, forced or not, refuse the directory for good."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    planned = planned_files(directory)
    for path in planned[4:]:  # as if killed at the fifth rename: the rest still staged
        path.rename(path.with_name(f".{path.name}.tmp"))
    with pytest.raises(SecureConfigError, match="already holds a secure profile"):
        init_secure(SecureInitConfig(directory))
    init_secure(SecureInitConfig(directory, force=True))
    assert sorted(p.name for p in directory.iterdir()) == sorted(p.name for p in planned)


@pytest.mark.skipif(os.geteuid() != 0, reason="needs root to give the directory to another user")
def test_a_directory_another_user_owns_is_refused(tmp_path, capsys):
    """Its owner could swap the profile's files (a CA, a config without an ACL) after they were checked."""
    directory = tmp_path / "profile"
    directory.mkdir(mode=0o777)
    os.chown(directory, 65534, 65534)
    rc, _, err = run_cli(capsys, "secure", "init", str(directory))
    assert rc == 2 and "is owned by uid 65534, not by this user" in err and list(directory.iterdir()) == []


def test_a_cut_short_swap_through_a_link_is_finished_by_force(tmp_path):
    """DIR a link to profiles/prod, whose forced init was killed between its folder renames (the old profile
    aside, prod gone): --force made the directory at the dangling link ("File exists") and left the old one."""
    real = tmp_path / "profiles" / "prod"
    real.mkdir(parents=True)
    link = tmp_path / "secure"
    link.symlink_to(real, target_is_directory=True)
    init_secure(SecureInitConfig(link))
    old = _files(real)
    os.rename(real, real.with_name(".prod.old-0badf00d"))  # as the crash between the renames leaves it
    with pytest.raises(SecureConfigError, match="old profile is whole in .*prod.old-0badf00d"):
        init_secure(SecureInitConfig(link))
    init_secure(SecureInitConfig(link, force=True))
    assert link.is_symlink() and sorted(p.name for p in real.parent.iterdir()) == ["prod"]
    _assert_whole_new_profile(real, old)


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


# ---------------------------------------------------------------- a folder that cannot be renamed: swapped inside it

def _profile_files(directory: Path) -> dict[str, bytes]:
    """``_files`` without the folders a swap inside ``directory`` makes."""
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir()) if not p.is_dir()}


@contextmanager
def _folder_swap_refused(monkeypatch: pytest.MonkeyPatch, directory: Path, at: str = "rename",
                         code: int = errno.EBUSY) -> Iterator[None]:
    """``directory`` cannot be renamed (``at="rename"``: as a mount point, EBUSY) or be given a sibling (``at="mkdir"``:
    as in a parent that may not be written); every other call is real."""
    target = directory.resolve()
    real = getattr(os, at)

    def refused_at(path: Path) -> bool:
        if at == "rename":
            return path == target
        return path.parent == target.parent and path.name.startswith(f".{target.name}.new-")

    def refused(path, *args, **kwargs):
        if refused_at(Path(path)):
            raise OSError(code, os.strerror(code), str(path))
        return real(path, *args, **kwargs)

    with monkeypatch.context() as m:
        m.setattr(os, at, refused)
        yield


@pytest.mark.parametrize(("at", "code"), [("rename", errno.EBUSY), ("rename", errno.EXDEV), ("rename", errno.EPERM),
                                          ("mkdir", errno.EACCES), ("mkdir", errno.EROFS)])
def test_a_folder_that_cannot_be_swapped_has_its_files_swapped_inside_it(monkeypatch, tmp_path, capsys, at, code):
    """A mount point (EBUSY), an overlay's lower layer (EXDEV), a parent that may not be written (EACCES, EROFS):
    ``--force`` still replaces the profile whole, in the same folder, and leaves nothing else."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old, inode = _files(directory), directory.stat().st_ino
    with _folder_swap_refused(monkeypatch, directory, at, code):
        rc, out, err = run_cli(capsys, "secure", "init", str(directory), "--force", "--json")
    assert rc == 0 and json.loads(out)["left_over"] is None and not err, (rc, err)
    _assert_whole_new_profile(directory, old)
    assert directory.stat().st_ino == inode and oct(directory.stat().st_mode & 0o777) == oct(0o700)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["profile"]


def test_a_rename_that_fails_anywhere_in_a_swap_inside_the_folder_leaves_the_old_profile_whole(monkeypatch,
                                                                                              tmp_path):
    """The folder is a mount point and each rename of the swap inside it fails in turn: the old profile stays, byte
    for byte, and neither the new files nor the folders of the swap are left behind."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old = _files(directory)
    with _folder_swap_refused(monkeypatch, directory):
        for call in range(2, 96):  # the 1st rename is the folder's, refused
            with _rename_fails_at(monkeypatch, call) as count:
                try:
                    init_secure(SecureInitConfig(directory, force=True))
                except OSError as exc:
                    assert "No space left on device" in str(exc)
                    assert _files(directory) == old, f"rename {call} failed: old and new files mixed"
                    assert sorted(p.name for p in tmp_path.iterdir()) == ["profile"], call
                    continue
            assert count[0] < call  # a run with no failed rename: done
            break
    assert call > 2 * len(planned_files(directory))  # every file's two renames were made to fail
    _assert_whole_new_profile(directory, old)


def test_when_the_old_files_cannot_be_put_back_inside_the_folder_the_error_says_where_they_are(monkeypatch,
                                                                                              tmp_path, capsys):
    """The first new file cannot be renamed into the mount point, nor the second old one back: the error names the
    folder that holds the old files not back; those and the one back in place make the old profile whole."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old, n = _files(directory), len(planned_files(directory))
    with _folder_swap_refused(monkeypatch, directory), _rename_fails_at(monkeypatch, n + 2, n + 4):
        rc, out, err = run_cli(capsys, "secure", "init", str(directory), "--force")
    lines = err.strip().splitlines()
    assert rc == 1 and not out and len(lines) == 1, (rc, out, err)
    [aside] = [p for p in directory.iterdir() if p.is_dir()]
    assert aside.name.startswith(".old-") and str(aside) in lines[0] and "move the files" in lines[0], lines[0]
    back = _profile_files(directory)
    assert len(back) == 1 and {**back, **_files(aside)} == old
    assert sorted(p.name for p in tmp_path.iterdir()) == ["profile"]


def test_old_files_that_cannot_be_deleted_after_a_swap_inside_the_folder_are_named(monkeypatch, tmp_path, capsys):
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old = _files(directory)
    with _folder_swap_refused(monkeypatch, directory), _undeletable(monkeypatch, ".old-"):
        rc, out, err = run_cli(capsys, "secure", "init", str(directory), "--force", "--json")
    [aside] = [p for p in directory.iterdir() if p.is_dir()]
    assert rc == 0 and json.loads(out)["left_over"] == str(aside) and _files(aside) == old
    assert "warning" in err and str(aside) in err, err
    assert _profile_files(directory).keys() == old.keys()


@pytest.mark.parametrize("kill_at", ["first aside", "middle aside", "first in", "middle in"])
def test_a_swap_inside_the_folder_killed_at_a_rename_never_mixes_profiles_and_force_finishes_it(tmp_path, capsys,
                                                                                              monkeypatch, kill_at):
    """After a real SIGKILL at a rename of the swap inside a mount point, the folder holds old files or new ones,
    never both. A plain init then names the swap's folders and asks for --force; --force replaces the profile
    whole and deletes them."""
    directory = tmp_path / "profile"
    init_secure(SecureInitConfig(directory))
    old, n = _files(directory), len(planned_files(directory))
    call = {"first aside": 2, "middle aside": 2 + n // 2, "first in": n + 2, "middle in": n + 2 + n // 2}[kill_at]
    done = subprocess.run([sys.executable, "-c", KILLED_AT_RENAME, str(directory), str(call), "busy"], cwd=REPO,
                          capture_output=True, text=True, timeout=120, env=ENV)
    assert done.returncode == -signal.SIGKILL, done.stderr
    left = _profile_files(directory)
    assert (all(old[name] == data for name, data in left.items())
            or all(old[name] != data for name, data in left.items())), "old and new files mixed"
    swaps = sorted(p.name for p in directory.iterdir() if p.is_dir())
    assert [name[:5] for name in swaps] == [".new-", ".old-"], swaps
    rc, out, err = run_cli(capsys, "secure", "init", str(directory))
    assert rc == 2 and all(name in err for name in swaps) and "--force" in err and "cut short" in err, err
    with _folder_swap_refused(monkeypatch, directory):
        rc, out, err = run_cli(capsys, "secure", "init", str(directory), "--force")
    assert rc == 0, err
    _assert_whole_new_profile(directory, old)


# ---------------------------------------------------------------- a real mount point

MOUNTED = r"""
set -e
P="$1/parent"; D="$P/profile"; PY="$2"
mkdir "$P"; mount -t tmpfs none "$P" || exit 77
mkdir "$D"; mount -t tmpfs -o mode=0700 none "$D" || exit 77
if [ "$3" = read-only-parent ]; then mount -o remount,ro "$P" || exit 77; fi
"$PY" -m orchestrator secure init "$D" > /dev/null
cp -a "$D" "$1/before"
"$PY" -m orchestrator secure init --force "$D" --json > "$1/force.json"
cp -a "$D" "$1/after"
"$PY" -m orchestrator secure check "$D/worker.json5" > /dev/null
mountpoint -q "$D"
"""


def _unshare_mount() -> list[str] | str:
    """The command that runs another in a mount namespace of its own, or why there is none here."""
    if not all(shutil.which(tool) for tool in ("unshare", "mount", "mountpoint")):
        return "needs util-linux's unshare, mount and mountpoint"
    command = ["unshare", "--mount"] if os.geteuid() == 0 else ["unshare", "--map-root-user", "--mount"]
    probe = subprocess.run([*command, "true"], capture_output=True, text=True, timeout=60)
    if probe.returncode != 0:
        return f"`{' '.join(command)}` is not permitted here: {probe.stderr.strip()}"
    return command


@pytest.mark.parametrize("case", ["mount-point", "read-only-parent"])
def test_a_forced_init_replaces_a_profile_in_a_real_mount_point(tmp_path, case):
    """A tmpfs mounted at the profile path (a Docker/Kubernetes volume), in a parent that may be written or not:
    `secure init --force` replaces the profile whole, in place, and the new one checks out there."""
    command = _unshare_mount()
    if isinstance(command, str):
        pytest.skip(command)
    done = subprocess.run([*command, "bash", "-c", MOUNTED, "mounted", str(tmp_path), sys.executable, case],
                          cwd=REPO, capture_output=True, text=True, timeout=300, env=ENV)
    if done.returncode == 77:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "force.json").read_text())["left_over"] is None
    old, new = _files(tmp_path / "before"), _files(tmp_path / "after")
    assert sorted(new) == sorted(old) and [name for name in new if new[name] == old[name]] == []
    ca = x509.load_pem_x509_certificate(new["ca.pem"])
    for role in ROLES:
        x509.load_pem_x509_certificate(new[f"{role}.pem"]).verify_directly_issued_by(ca)
