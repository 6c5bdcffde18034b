"""The package's layers (pyproject.toml [tool.importlinter]): nothing imports upward, and the check can fail."""

import os
import shutil
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _lint(cwd: str) -> subprocess.CompletedProcess:
    exe = shutil.which("lint-imports", path=os.path.dirname(sys.executable)) or shutil.which("lint-imports")
    assert exe, "import-linter is not installed (pip install -e '.[test]')"
    env = {**os.environ, "PYTHONPATH": cwd}
    return subprocess.run([exe, "--no-cache"], cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_no_module_imports_a_higher_layer():
    res = _lint(ROOT)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert "1 kept, 0 broken" in res.stdout


def test_an_upward_import_inside_a_function_breaks_the_contract(tmp_path):
    shutil.copytree(os.path.join(ROOT, "gpd_jax"), tmp_path / "gpd_jax",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(os.path.join(ROOT, "pyproject.toml"), tmp_path / "pyproject.toml")
    with open(tmp_path / "gpd_jax" / "scene.py", "a") as f:  # the bottom layer reaching for evaluation
        f.write("\n\ndef _upward():\n    from gpd_jax.evaluation import evaluate\n    return evaluate\n")
    res = _lint(str(tmp_path))
    assert res.returncode != 0
    assert "gpd_jax.scene -> gpd_jax.evaluation" in res.stdout.replace("\n", " ") or "BROKEN" in res.stdout.upper()
