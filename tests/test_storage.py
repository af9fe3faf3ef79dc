"""The output folder on an unmounted card: nothing made or recorded on the root filesystem underneath it."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
import time
import zlib
from pathlib import Path

import pytest

import logger.recording.storage as storage
from logger.recording.files import walk
from logger.recording.recorder import Recorder
from logger.recording.settings import RecorderSettings
from logger.recording.storage import fstab_mount_points, mounted_points, storage_problem
from logger.recording.topics import TOPICS

FSTAB_TEXT = """# /etc/fstab: static file system information.
UUID=4c3e-root  /               ext4    noatime,errors=remount-ro 0 1
/dev/mmcblk0p2  none            swap    sw                       0 0
LABEL=DRIVES    {card}          ext4    noatime,nofail,x-systemd.device-timeout=5s 0 2
LABEL=MY\\040DISK /media/my\\040disk vfat defaults,nofail 0 0
tmpfs           /tmp            tmpfs   defaults                 0 0
"""


def mountinfo_line(point: Path | str, device: str | None = None) -> str:
    """A mountinfo line; each mount point a filesystem of its own (its device) unless ``device`` is given."""
    where = str(point).replace(" ", "\\040")
    device = device or ("179:2" if str(point) == "/" else f"8:{zlib.crc32(str(point).encode()) % 250 + 1}")
    return f"36 25 {device} / {where} rw,noatime shared:7 - ext4 /dev/mmcblk1p1 rw\n"


def tables(tmp_path: Path, card: Path, mounted: bool) -> tuple[Path, Path]:
    fstab, info = tmp_path / "fstab", tmp_path / "mountinfo"
    fstab.write_text(FSTAB_TEXT.format(card=card))
    info.write_text(mountinfo_line("/") + mountinfo_line("/tmp") + (mountinfo_line(card) if mounted else ""))
    return fstab, info


def test_fstab_and_mountinfo_are_read_as_the_kernel_and_mount_write_them(tmp_path: Path) -> None:
    card = tmp_path / "card"
    fstab, info = tables(tmp_path, card, mounted=True)
    # The root and swap are no storage of their own; escapes are undone.
    assert fstab_mount_points(fstab.read_text()) == [card, Path("/media/my disk"), Path("/tmp")]
    assert mounted_points(info.read_text()) == {Path("/"), Path("/tmp"), card}
    assert mounted_points(mountinfo_line("/media/my disk")) == {Path("/media/my disk")}


def test_a_folder_under_an_unmounted_fstab_entry_is_refused_naming_its_mount_point(tmp_path: Path) -> None:
    card = tmp_path / "card"
    fstab, info = tables(tmp_path, card, mounted=False)
    problem = storage_problem(card / "drives", fstab, info)
    assert problem == f"{card} is not mounted (listed in /etc/fstab); waiting for it"
    assert storage_problem(card, fstab, info) is not None  # the mount point itself
    assert storage_problem(card / ".." / "card" / "a" / "b", fstab, info) is not None  # however it is written
    # Mounted, or not under any listed storage, or nothing known: nothing against the folder.
    fstab, info = tables(tmp_path, card, mounted=True)
    assert storage_problem(card / "drives", fstab, info) is None
    assert storage_problem(tmp_path / "elsewhere", fstab, info) is None
    assert storage_problem(card / "drives", tmp_path / "no-fstab", info) is None
    assert storage_problem(card / "drives", fstab, tmp_path / "no-proc") is None


def test_the_innermost_listed_mount_point_is_the_one_that_must_be_mounted(tmp_path: Path) -> None:
    """A card mounted inside a disk's mount point: the disk mounted and the card not is no place to record."""
    disk, card = tmp_path / "disk", tmp_path / "disk" / "card"
    fstab, info = tmp_path / "fstab", tmp_path / "mountinfo"
    fstab.write_text(f"/dev/sda1 {disk} ext4 defaults 0 2\n/dev/mmcblk1p1 {card} ext4 nofail 0 2\n")
    info.write_text(mountinfo_line("/") + mountinfo_line(disk))
    assert str(card) in (storage_problem(card / "drives", fstab, info) or "")
    assert storage_problem(disk / "other", fstab, info) is None


def test_the_service_s_own_bind_of_the_mount_point_is_not_the_card(tmp_path: Path) -> None:
    """The unit's drop-in ``ReadWritePaths=`` binds the mount point onto itself in the service's namespace, so it is
    always in the service's mount table: the root filesystem's own folder there is no card (the service recorded on
    the root filesystem, status OK, the file hidden once the card was mounted). A card mounted over the bind, or
    one mounted before the service started (the bind is then of the card), is."""
    card = tmp_path / "card"
    fstab, info = tables(tmp_path, card, mounted=False)
    info.write_text(mountinfo_line("/") + mountinfo_line(card, "179:2"))  # the root's folder bound onto itself
    assert storage_problem(card / "drives", fstab, info) == f"{card} is not mounted (listed in /etc/fstab); waiting " \
        "for it"
    info.write_text(mountinfo_line("/") + mountinfo_line(card, "179:2") + mountinfo_line(card, "179:33"))
    assert storage_problem(card / "drives", fstab, info) is None  # mounted later, over the bind
    info.write_text(mountinfo_line("/") + mountinfo_line(card, "179:33") + mountinfo_line(card, "179:33"))
    assert storage_problem(card / "drives", fstab, info) is None  # mounted first, then bound
    # A bind mount that fstab itself lists is the storage it names, whatever filesystem it is on.
    fstab.write_text(f"/srv/drives {card} none bind,nofail 0 0\n")
    info.write_text(mountinfo_line("/") + mountinfo_line(card, "179:2"))
    assert storage_problem(card / "drives", fstab, info) is None
    info.write_text(mountinfo_line("/"))
    assert storage_problem(card / "drives", fstab, info) is not None


def _private_mount_namespace() -> bool:
    """Whether this host can make a mount namespace of its own with private propagation: root, unshare, and a root
    that is a mount point (not so in a chroot, as tools/board-check.sh's armhf root: "cannot change root
    filesystem propagation")."""
    if os.geteuid() != 0 or shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "-m", "--propagation", "private", "true"], capture_output=True).returncode == 0


@pytest.mark.skipif(not _private_mount_namespace(),
                    reason="needs root: a mount namespace of its own (unshare -m), as the service has, on a root "
                           "that is a mount point (not a chroot)")
def test_a_bind_of_the_mount_point_onto_itself_in_a_real_namespace_is_not_mounted_storage(tmp_path: Path) -> None:
    """The same, read from the kernel's own table: a mount namespace with the empty mount point bound onto itself
    (what systemd makes of ``ReadWritePaths=``), then a tmpfs mounted over it (the card)."""
    card = tmp_path / "card"
    card.mkdir()
    fstab = tmp_path / "fstab"
    fstab.write_text(f"LABEL=DRIVES {card} ext4 nofail 0 2\n")
    ask = ("import sys; from pathlib import Path; from logger.recording.storage import storage_problem; "
           "print(storage_problem(Path(sys.argv[1]), Path(sys.argv[2])))")
    script = (f'mount --bind "$1" "$1" && {sys.executable} -c "$2" "$1/drives" "$3" '
              f'&& mount -t tmpfs -o size=1m card "$1" && {sys.executable} -c "$2" "$1/drives" "$3"')
    r = subprocess.run(["unshare", "-m", "--propagation", "private", "sh", "-c", script, "sh", str(card), ask,
                        str(fstab)], capture_output=True, text=True, timeout=60,
                       cwd=Path(__file__).resolve().parents[1])
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == [f"{card} is not mounted (listed in /etc/fstab); waiting for it", "None"]


def wait_until(predicate, timeout_s: float = 20.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.02)
    return False


def test_the_recorder_waits_for_its_card_and_never_records_underneath_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """The card not mounted at start (left out, a failed mount): the recorder makes nothing in its empty mount
    point and says why, once; mounted, it records there. Lost while recording (a lazy unmount of a dying card: the
    folder is gone from the mount point), it does not make the folder again on the root filesystem, and records
    again once the card is back."""
    import logger.recording.recorder as recorder_module

    card = tmp_path / "card"
    card.mkdir()  # the empty mount point, on the root filesystem
    out = card / "drives"
    fstab, info = tables(tmp_path, card, mounted=False)
    monkeypatch.setattr(storage, "FSTAB", fstab)
    monkeypatch.setattr(storage, "MOUNTINFO", info)
    monkeypatch.setattr(recorder_module, "RETRY_S", 0.0)
    rec = Recorder(RecorderSettings(out_dir=out, flush_interval_s=0.02), TOPICS)
    assert rec.start() is None
    try:
        for i in range(20):
            rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, i)
            time.sleep(0.01)
        st = rec.status()
        assert st.state == "failed" and st.detail.startswith(f"not recording: {card} is not mounted"), st
        assert list(card.iterdir()) == []  # nothing made underneath the mount point
        assert caplog.text.count("is not mounted") == 1  # said once, not at every retry
        assert (f"not recording into {out}, which would be made on the filesystem underneath: {card} is not mounted "
                "(listed in /etc/fstab); checking again every 0 s") in caplog.text

        info.write_text(mountinfo_line("/") + mountinfo_line(card))  # the card mounted
        i = 100
        while rec.status().state != "recording" and i < 2000:
            rec.submit("/a", {"x": i}, 1_700_000_000_000_000_000 + i, i)
            i += 1
            time.sleep(0.01)
        assert rec.status().state == "recording"
        for k in range(5):
            rec.submit("/a", {"x": k}, 1_700_000_000_500_000_000 + k, 10_000 + k)
        (first,) = out.glob("*.mcap")
        assert wait_until(lambda: walk(first).messages != [])

        # The card lost while recording: its folder gone from the mount point, the mount gone from the table.
        info.write_text(mountinfo_line("/"))
        for f in out.iterdir():
            f.unlink()
        out.rmdir()
        for j in range(50):
            rec.submit("/a", {"x": j}, 1_700_000_001_000_000_000 + j, j)
            time.sleep(0.01)
        assert wait_until(lambda: rec.status().state == "failed"), rec.status()
        assert wait_until(lambda: "is not mounted" in rec.status().detail), rec.status()
        assert not out.exists()  # not made again on the root filesystem
    finally:
        rec.stop()


def test_the_daemon_runs_without_its_card_says_so_and_records_once_it_is_mounted(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """A board booted without its card (fstab's nofail): the sensors, the filter and the status run; the status
    names the missing mount as the recorder's problem (the operator sees at once that nothing is kept) and nothing
    is made under the mount point; the card mounted, recording starts there."""
    from logger.compose import build
    from logger.config import defaults
    from logger.runtime.status_socket import fetch

    card = tmp_path / "card"
    card.mkdir()
    fstab, info = tables(tmp_path, card, mounted=False)
    monkeypatch.setattr(storage, "FSTAB", fstab)
    monkeypatch.setattr(storage, "MOUNTINFO", info)
    cfg = defaults(sim=True)
    sock = tmp_path / "status.sock"
    cfg.values["logger"].update(out_dir=str(card / "drives"), status_socket=str(sock), state_dir=str(tmp_path / "s"))
    cfg.values["sim"]["time_scale"] = 4.0
    daemon, _ = build(cfg, duration_s=3600)
    daemon.start()
    try:
        assert wait_until(lambda: fetch(sock)["recorder"]["state"] == "failed")
        snap = fetch(sock)
        assert snap["verdict"] == "critical"
        assert any(p.startswith(f"recorder: not recording: {card} is not mounted") for p in snap["problems"]), snap
        assert wait_until(lambda: all(s.health.samples > 0 for s in daemon.samplers))  # the sensors run
        assert list(card.iterdir()) == []
        assert f"started without recording into {card / 'drives'}" in caplog.text
        # A wait for the card, not a writer failing by itself: past the heartbeat bound the watchdog is still
        # answered (systemd restarting the service every minute and a half could not bring the card back).
        assert snap["recorder"]["storage_missing"] is True and snap["recorder"]["free_bytes"] is None
        # Only the recorder's lines are this test's: a loaded host slows the paced drive, and a 1 Hz sensor then
        # beats less often than so short a bound (sampler-baro "silent for 1 s" in a CI run).
        daemon.heartbeat_bound_s = 0.5
        time.sleep(1.0)
        assert not [line for line in daemon.stale_threads() if line.startswith("recorder failing")]
        status = daemon.recorder.status
        with monkeypatch.context() as m:  # the same failure with the card there would stop the watchdog
            m.setattr(daemon.recorder, "status", lambda: dataclasses.replace(status(), storage_missing=False))
            assert [line for line in daemon.stale_threads() if line.startswith("recorder failing")]

        info.write_text(mountinfo_line("/") + mountinfo_line(card))
        assert wait_until(lambda: fetch(sock)["recorder"]["state"] == "recording", 30.0), fetch(sock)["recorder"]
        assert list((card / "drives").glob("*.mcap"))
    finally:
        daemon.stop()
