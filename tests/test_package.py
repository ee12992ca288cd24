"""surftrack as a package people install: an sdist and the wheel built from it carry the configs and the
bundled model, and the installed tool works from a directory outside the checkout."""

from __future__ import annotations

import os
import site
import subprocess
import sys
import sysconfig
import tarfile
import venv
from pathlib import Path

import pytest

import surftrack

ROOT = Path(__file__).resolve().parent.parent


def test_every_subpackage_is_packaged():
    """pyproject.toml lists the packages explicitly (configs/ and models/ are mapped into the package):
    a new sub-package of surftrack must be listed, or a wheel would lack it."""
    tomllib = pytest.importorskip("tomllib", reason="tomllib is in the standard library from Python 3.11")
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {".".join(p.parent.relative_to(ROOT).parts) for p in (ROOT / "surftrack").rglob("__init__.py")}
    assert found <= listed, f"add {sorted(found - listed)} to [tool.setuptools] packages in pyproject.toml"


def _run(cmd: list[str], cwd: Path, env: dict[str, str]) -> str:
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"{' '.join(cmd)} exited {r.returncode}:\n{r.stdout}\n{r.stderr}"
    return r.stdout


def test_wheel_installed_outside_the_checkout(tmp_path):
    """Build an sdist, build the wheel from the unpacked sdist (as pip does for an sdist), install it into
    a fresh virtual environment and run the tool from another directory: every built-in instrument, the
    bundled model, the demo on a tiny clip and eval's help. The new environment borrows this one's
    dependencies through a .pth line (no network), not its surftrack."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("SURFTRACK_")}
    dist = tmp_path / "dist"
    dist.mkdir()
    name = _run([sys.executable, "-c", "import sys; from setuptools import build_meta; "
                 "print(build_meta.build_sdist(sys.argv[1]))", str(dist)], ROOT, env).strip().splitlines()[-1]
    with tarfile.open(dist / name) as tar:
        tar.extractall(tmp_path / "src", **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
    src = next((tmp_path / "src").iterdir())
    _run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation", "--no-index",
          "-w", str(dist), str(src)], tmp_path, env)
    wheel = next(dist.glob("surftrack-*.whl"))

    target = tmp_path / "venv"
    venv.create(target, with_pip=False)
    py = target / "bin" / "python"
    site_dir = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"], tmp_path, env)
                .strip())
    here = {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"], *site.getsitepackages()}
    (site_dir / "borrowed_dependencies.pth").write_text("".join(f"{p}\n" for p in sorted(here)))
    _run([sys.executable, "-m", "pip", "--python", str(py), "install", "--quiet", "--no-deps", "--no-index",
          str(wheel)], tmp_path, env)

    work = tmp_path / "elsewhere"
    work.mkdir()
    tool = str(target / "bin" / "surftrack")
    where = _run([str(py), "-c", "import surftrack, surftrack.paths as p; print(surftrack.__file__); "
                  "print(p.default_model_path()); print(p.configs_dir())"], work, env).split()
    assert all(Path(w).is_relative_to(site_dir) for w in where), where  # the installed copy, not the checkout
    assert _run([tool, "--version"], work, env).strip() == f"surftrack {surftrack.__version__}"
    listed = _run([tool, "instruments"], work, env)
    for name in ("large_needle_driver", "cadiere_forceps", "biopsy_forceps", "scissors",
                 "permanent_cautery_spatula", "small_clip_applier"):
        assert f"\n{name} (" in "\n" + listed
    out = _run([tool, "demo", "--out", str(work / "demo"), "--seconds", "2", "--fps", "5", "--quiet"], work, env)
    assert "accuracy against the ground truth" in out
    assert (work / "demo" / "summary.json").is_file() and (work / "demo" / "tracks.mcap").is_file()
    assert "--kinematic" in _run([tool, "eval", "--help"], work, env)
