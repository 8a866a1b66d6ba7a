"""A wheel and an sdist built from the repository's files install into a fresh virtual environment (with the CPU
build of torch first, as scripts/bootstrap.sh installs it), with the compiled kernel; `contact-viz --version` and
the README's Python example run there, and the `notebook` extra brings rerun-notebook."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def tracked_files() -> list[Path]:
    """The repository's files as a clean checkout has them (git ls-files; without git: the source tree)."""
    done = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True)
    if done.returncode == 0 and done.stdout:
        return [Path(p) for p in done.stdout.decode().split("\0") if p and (ROOT / p).is_file()]
    return [p.relative_to(ROOT) for p in ROOT.rglob("*") if p.is_file()
            and not {".venv", ".git", "demo", "build", "__pycache__"} & set(p.relative_to(ROOT).parts)]


def run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    done = subprocess.run(cmd, capture_output=True, text=True, **kwargs)
    assert done.returncode == 0, f"{' '.join(map(str, cmd))}:\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    source = tmp / "src_copy"
    for rel in tracked_files():
        (source / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / rel, source / rel)
    # the sdist first, then the wheel built from the sdist (python -m build's default): a broken sdist fails here
    run([sys.executable, "-m", "build", "--outdir", str(tmp / "dist"), str(source)])
    return tmp, sorted((tmp / "dist").glob("*.whl")), sorted((tmp / "dist").glob("*.tar.gz"))


def test_the_wheel_holds_the_compiled_kernel_and_the_sdist_its_source(built):
    _, wheels, sdists = built
    assert len(wheels) == 1 and len(sdists) == 1
    names = zipfile.ZipFile(wheels[0]).namelist()
    assert any(re.fullmatch(r"contact_viz/geometry/_patch_kernels\..*\.so", n) for n in names)
    assert "contact_viz/api.py" in names and any(n.endswith("entry_points.txt") for n in names)
    import tarfile

    members = tarfile.open(sdists[0]).getnames()
    assert any(m.endswith("src/contact_viz/geometry/_patch_kernels.pyx") for m in members)
    assert not any(m.endswith("_patch_kernels.c") for m in members)  # generated: built from the .pyx


def test_the_wheel_installs_and_runs_in_a_fresh_environment(built):
    tmp, wheels, _ = built
    venv = tmp / "venv"
    run([sys.executable, "-m", "venv", str(venv)])
    pip, python = venv / "bin" / "pip", venv / "bin" / "python"
    run([str(pip), "install", "-q", "torch==2.13.0"])  # the CPU build, as bootstrap.sh does
    run([str(pip), "install", "-q", f"{wheels[0]}[notebook]"])
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{venv / 'bin'}:{env.get('PATH', '')}"
    env["CONTACT_VIZ_CACHE"] = str(tmp / "cache")
    from contact_viz import __version__

    assert run([str(venv / "bin" / "contact-viz"), "--version"], env=env, cwd=tmp).stdout.strip() == \
        f"contact-viz {__version__}"
    where = run([str(python), "-c", "import contact_viz, contact_viz.geometry._patch_kernels as k, rerun_notebook; "
                 "print(contact_viz.__file__); print(k.__file__)"], env=env, cwd=tmp).stdout.split()
    assert all(str(venv) in w for w in where)  # the installed package, not this checkout
    text = (ROOT / "README.md").read_text()
    section = text[text.index("## From Python"):]
    (block,) = re.findall(r"```python\n(.*?)```", section[:section.index("\n## ", 3)], flags=re.S)
    done = run([str(python), "-c", block], env=env, cwd=tmp)
    assert "'frame': '000020'" in done.stdout
