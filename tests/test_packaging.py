"""The installed package, as a user gets it from a plain ``pip install .`` (not editable).

One top-level name, ``anklescan`` (the folders core/, hardware/ and app/ are mapped to
anklescan.core/.hardware/.app), every subpackage shipped, the icons as package data, and the
GUI starting from the installed copy with its icon.
"""

import os
import shutil
import subprocess
import sys
import sysconfig
import tomllib
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_every_subpackage_is_listed_in_pyproject():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"anklescan." + ".".join(p.parent.relative_to(ROOT).parts)
             for top in ("core", "hardware", "app", "resources") for p in (ROOT / top).rglob("__init__.py")}
    assert found | {"anklescan.docs"} == listed  # docs/: package data only (the user guide), no module


@pytest.fixture(scope="module")
def wheel(tmp_path_factory):
    # built from a copy: setuptools leaves build/ in the source tree, and a stale build/lib there
    # (a module since moved) would be packed into the next wheel
    src, out = tmp_path_factory.mktemp("src"), tmp_path_factory.mktemp("wheel")
    for name in ("core", "hardware", "app", "resources", "docs"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out), str(src)],
                   check=True, capture_output=True, timeout=300)
    (whl,) = out.glob("anklescan-*.whl")
    return whl


def test_the_wheel_holds_only_anklescan_and_its_icon(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    assert {n.split("/")[0] for n in names} == {"anklescan", wheel.name.split("-py")[0] + ".dist-info"}
    assert "anklescan/resources/anklescan.svg" in names
    assert "anklescan/resources/calibration_box.json" in names
    assert "anklescan/docs/gui.md" in names  # Help ▸ User guide, offline
    sources = {str(p.relative_to(ROOT)) for top in ("core", "hardware", "app") for p in (ROOT / top).rglob("*.py")}
    assert {"anklescan/" + s for s in sources} <= set(names)


@pytest.mark.slow
@pytest.mark.gui  # the GUI check needs the X server pytest-xvfb starts
def test_a_plain_install_runs_the_gui_with_its_icon(wheel, tmp_path):
    env_dir = tmp_path / "venv"
    venv.create(env_dir, with_pip=True)
    py = env_dir / "bin" / "python"
    # The dependencies from the environment running the tests, not from the base interpreter
    # (``system_site_packages``): on a clean machine only the CI's venv holds PySide6. A path in
    # a .pth file is added after the venv's own site-packages, and the .pth files in it (this
    # checkout's editable install) are not read, so anklescan comes from the wheel.
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          check=True, capture_output=True, text=True).stdout.strip()
    here = {sysconfig.get_paths()[k] for k in ("purelib", "platlib")}
    (Path(site) / "test_environment.pth").write_text("\n".join(sorted(here)) + "\n")
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", str(wheel)], check=True,
                   capture_output=True, timeout=300)
    env = {**os.environ, "ANKLESCAN_SETTINGS": str(tmp_path / "s.ini"), "ANKLESCAN_DATA": str(tmp_path / "data"),
           "QT_QPA_PLATFORM": "xcb", "PYTHONPATH": ""}
    where = subprocess.run([str(py), "-c", "import anklescan.app.resources as r; print(r.ICONS)"], cwd=tmp_path,
                           env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert Path(where).is_relative_to(env_dir) and (Path(where) / "anklescan.svg").is_file()
    guide = subprocess.run([str(py), "-c", "from anklescan.app.help_menu import docs_folder; print(docs_folder())"],
                           cwd=tmp_path, env=env, capture_output=True, text=True, check=True).stdout.strip()
    assert Path(guide).is_relative_to(env_dir) and (Path(guide) / "gui.md").is_file()
    assert (env_dir / "bin" / "anklescan").is_file()  # the console script
    gui = subprocess.run([str(py), "-c", "import sys; from anklescan.app.main_window import run_gui; "
                          "sys.exit(run_gui(['anklescan', '--quit-when-shown']))"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=120)
    assert gui.returncode == 0, gui.stderr
    assert "first window shown" in gui.stdout
    assert "Cannot open file" not in gui.stderr and "anklescan.svg" not in gui.stderr
