"""vbnav teach / repeat as commands: a short teach, a repeat, and bad routes refused before the motors."""
import json
import subprocess
import sys

VBNAV = [sys.executable, "-m", "vbnav.control.cli"]


def test_teach_writes_route_and_repeat_rejects_foreign_dirs(tmp_path):
    route = tmp_path / "route"
    r = subprocess.run(VBNAV + ["teach", "--out", str(route), "--duration", "6"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    manifest = json.loads((route / "manifest.json").read_text())
    assert manifest["format"] == "vbnav-route" and len(manifest["keyframes"]) >= 3
    # A repeat of that short route runs to its end.
    r = subprocess.run(VBNAV + ["repeat", "--path", str(route), "--duration", "60"], capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "repeat ended: finished" in r.stdout
    # A foreign directory and a corrupt manifest are refused with the file named, before any motion.
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("hello")
    r = subprocess.run(VBNAV + ["repeat", "--path", str(foreign)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "manifest.json" in r.stdout + r.stderr
    (route / "manifest.json").write_text("{ not json")
    r = subprocess.run(VBNAV + ["repeat", "--path", str(route)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "manifest.json" in r.stdout + r.stderr
    assert "repeat ended" not in r.stdout
