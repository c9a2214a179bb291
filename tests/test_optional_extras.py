"""Optional SDKs: without depthai (the vbnav[oak] extra) the OAK driver says which extra to install.

depthai stays installed here; a meta-path finder in a fresh interpreter makes it unimportable.
"""
from __future__ import annotations

import subprocess
import sys
import textwrap

from vbnav.control.config import CONFIG_DIR

HINT = "the OAK camera driver needs depthai: pip install 'vbnav[oak]'"

BLOCK_DEPTHAI = textwrap.dedent("""
    import sys

    class NoDepthai:
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] == "depthai":
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, NoDepthai())
""")


def _without_depthai(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", BLOCK_DEPTHAI + textwrap.dedent(code)],
                          capture_output=True, text=True, timeout=120)


def test_importing_the_oak_driver_without_depthai_names_the_extra():
    r = _without_depthai("""
        try:
            import vbnav.drivers.oak_camera
        except ImportError as exc:
            print(exc)
        else:
            raise SystemExit("imported without depthai")
    """)
    assert r.returncode == 0, r.stderr
    assert HINT in r.stdout


def test_choosing_the_oak_driver_without_depthai_names_the_extra():
    r = _without_depthai(f"""
        from vbnav.drivers import registry
        from vbnav.control.config import ConfigError, load_config
        try:
            registry.load(registry.CAMERAS, "oak")
        except registry.DriverNotAvailable as exc:
            print(exc)
        try:
            load_config({str(CONFIG_DIR / "sentry-oak.yaml")!r})
        except ConfigError as exc:
            print(exc)
        import vbnav.drivers.v4l2_camera        # the other drivers do not need it
        registry.load(registry.CAMERAS, "v4l2")
    """)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    assert len(lines) == 2 and all(HINT in line for line in lines), r.stdout
    assert "sentry-oak.yaml: camera.driver:" in lines[1]
