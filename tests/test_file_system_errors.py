"""A file-system error (no permission, a file where a folder is expected, a read-only or full
file system) is one line in every command: the path, what the system said, what it means and
the option (or argument) the user gave that path by (cloudpose.failures.file_system_message,
the CLI's one handler)."""

from __future__ import annotations

import errno
import io
import os
import shutil
import tarfile
from pathlib import Path

import pytest

from cloudpose.failures import DiskFullError, file_system_message, is_file_system_error
from tests.conftest import cli, one_line_error

FRAME = Path(__file__).resolve().parents[1] / "cloudpose/resources/real_dev/data/0000/000001"

CLASSES = [
    (errno.ENOTDIR, "a part of the path is a file, not a folder"),
    (errno.EACCES, "no permission"),
    (errno.EPERM, "not permitted"),
    (errno.EROFS, "a read-only file system"),
    (errno.ENOSPC, "no space left"),
    (errno.EISDIR, "a folder where a file was expected"),
    (errno.ENOENT, "no such file or folder"),
]


@pytest.mark.parametrize(("code", "words"), CLASSES)
def test_each_class_is_one_line_naming_the_path_and_the_option(code, words):
    exc = OSError(code, os.strerror(code), "/some/where/out")
    message = file_system_message(exc, "--into")
    assert message.startswith(f"/some/where/out: {os.strerror(code)} (") and words in message
    assert "--into" in message and "\n" not in message


def test_without_an_option_the_message_names_none():
    message = file_system_message(OSError(errno.EACCES, "Permission denied", "/x/y"))
    assert message.startswith("/x/y: Permission denied (no permission") and "--" not in message


def test_a_file_where_a_folder_is_expected_is_said_so(tmp_path):
    blocker = tmp_path / "afile"
    blocker.write_text("")
    message = file_system_message(FileExistsError(errno.EEXIST, "File exists", str(blocker)))
    assert "a file, not a folder" in message


def test_only_the_systems_errors_about_a_path_take_the_file_system_form():
    assert is_file_system_error(PermissionError(errno.EACCES, "Permission denied", "/x"))
    assert is_file_system_error(FileNotFoundError(errno.ENOENT, "No such file", "/x"))
    assert not is_file_system_error(FileNotFoundError("/x: no such run folder"))  # the library's
    assert not is_file_system_error(FileExistsError("/x exists: --force replaces it"))
    assert not is_file_system_error(ConnectionRefusedError(errno.ECONNREFUSED, "refused"))
    assert not is_file_system_error(DiskFullError("/x"))  # its own message
    assert not is_file_system_error(ValueError("no"))


# -- in the commands: the option the user gave -----------------------------------------------


@pytest.fixture
def blocker(tmp_path, monkeypatch) -> Path:
    """A file where the commands below are told to make a folder; cwd an empty folder."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    path = tmp_path / "afile"
    path.write_text("")
    return path


def _archive(path: Path) -> Path:
    """A .tar.xz holding one (empty) mlflow.db: enough to get past the archive's checks."""
    with tarfile.open(path, "w:xz") as tar:
        info = tarfile.TarInfo("mlflow.db")
        tar.addfile(info, io.BytesIO(b""))
    return path


def test_store_unpack_names_into(blocker, tmp_path):
    res = cli("store-unpack", str(_archive(tmp_path / "s.tar.xz")), "--into", f"{blocker}/x")
    line = one_line_error(res, str(blocker), "--into", "a file, not a folder")
    assert "--out" not in line


@pytest.mark.parametrize("name", ["st", "st.tar.xz"])
def test_store_pack_names_its_out_argument(blocker, empty_store, name):
    shutil.copy(empty_store, Path.cwd() / "mlflow.db")
    res = cli("store-pack", f"{blocker}/{name}")
    line = one_line_error(res, str(blocker), "OUT", "a file, not a folder")
    assert "--out" not in line and "[Errno" not in line


def test_predict_names_overlay_before_any_work(blocker, monkeypatch):
    from cloudpose import predict

    def no_work(*a, **k):
        raise AssertionError("the network was loaded before the overlay's folder was checked")

    monkeypatch.setattr(predict, "load_model_for", no_work)
    res = cli(
        "predict",
        "--depth",
        f"{FRAME}-depth.png",
        "--label",
        f"{FRAME}-label.png",
        "--checkpoint",
        "pretrained",
        "--overlay",
        f"{blocker}/p.png",
    )
    line = one_line_error(res, str(blocker), "--overlay", "a file, not a folder")
    assert "[Errno" not in line


@pytest.mark.parametrize(("code", "words"), CLASSES[1:4])
def test_a_folder_the_system_refuses_names_the_option(code, words, tmp_path, monkeypatch):
    """No permission, not permitted (chattr +i) and a read-only file system, as the system
    raises them making the folder (root writes into any folder: they are raised here)."""
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    locked = tmp_path / "locked"
    mkdir = Path.mkdir

    def refused(self, *a, **k):
        if self == locked or locked in self.parents:
            raise OSError(code, os.strerror(code), str(self))
        return mkdir(self, *a, **k)

    monkeypatch.setattr(Path, "mkdir", refused)
    res = cli("store-unpack", str(_archive(tmp_path / "s.tar.xz")), "--into", f"{locked}/x")
    one_line_error(res, str(locked / "x"), "--into", words)


def test_a_temporary_file_beside_the_out_argument_names_it(tmp_path, monkeypatch, empty_store):
    """store-pack writes OUT.tar.xz through a temporary file beside it: the system's refusal of
    that file (chattr +i on the folder) names OUT, the argument the user gave."""
    import tarfile

    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.chdir(tmp_path)
    shutil.copy(empty_store, tmp_path / "mlflow.db")
    locked = tmp_path / "locked"
    locked.mkdir()
    opened = tarfile.open

    def refused(name=None, mode="r", *a, **k):
        if name is not None and Path(name).parent == locked:
            raise PermissionError(errno.EPERM, os.strerror(errno.EPERM), str(name))
        return opened(name, mode, *a, **k)

    monkeypatch.setattr(tarfile, "open", refused)
    res = cli("store-pack", str(locked / "st.tar.xz"))
    one_line_error(res, str(locked / ".st.tar.xz."), "not permitted", "choose another OUT")
