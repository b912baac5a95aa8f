"""The wheel is the whole toolkit: build it, install it into a fresh venv, use it from elsewhere.

The fresh venv reuses the dependencies already installed in this interpreter's environment (a
``.pth`` file pointing at its site-packages, whose own ``.pth`` files, among them the editable
selenv, are not processed), gets the wheel with ``--no-deps`` and runs, from an empty folder:
a shipped policy, a shipped surrogate's fusion step and ``selenv bench`` on one env.
"""

from __future__ import annotations

import os
import sys
import sysconfig
import zipfile
from pathlib import Path

import _proc
import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.slow


def _run(cmd: list[str], cwd: Path, env: dict[str, str] | None = None) -> str:
    proc = _proc.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, f"{cmd} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, Path, Path]:
    tmp = tmp_path_factory.mktemp("wheel")
    dist = tmp / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
          "--quiet", "-w", str(dist), str(ROOT)], cwd=tmp)  # fmt: skip
    (wheel,) = dist.glob("selenv-*.whl")
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", str(venv)], cwd=tmp)
    py = venv / "bin" / "python"
    site = Path(_run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                     cwd=tmp).strip())  # fmt: skip
    (site / "_selenv_test_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([str(py), "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", str(wheel)],
         cwd=tmp)  # fmt: skip
    work = tmp / "elsewhere"
    work.mkdir()
    return wheel, venv, work


def _env() -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}
    env["MPLBACKEND"] = "Agg"
    return env


def test_wheel_has_checkpoints_and_one_top_level_name(installed):
    wheel, _, _ = installed
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"selenv"}  # no generic 'train' / 'learned' / 'checkpoints'
    shipped = {
        p.name for p in (ROOT / "checkpoints").iterdir() if p.is_file() and p.suffix != ".py"
    }
    packaged = {n.split("/")[-1] for n in names if n.startswith("selenv/checkpoints/")}
    assert shipped <= packaged
    assert not [n for n in names if "__pycache__" in n or n.endswith(".pyc")]  # no byte code


def test_installed_wheel_runs_from_another_folder(installed):
    _, venv, work = installed
    py = str(venv / "bin" / "python")
    code = r"""
import gymnasium as gym, numpy as np, selenv
from pathlib import Path
assert Path(selenv.__file__).is_relative_to(Path(r"VENV")), selenv.__file__
for name in ("learned", "train"):
    try:
        __import__(name)
    except ImportError:
        pass
    else:
        raise AssertionError(f"generic top-level package {name!r} is importable")
from selenv.agents import make
env = gym.make("selenv/FIMSelection-v1", n_candidates=20, budget=3)
agent = make("ppo", "selenv/FIMSelection-v1")
obs, info = env.reset(seed=0); agent.reset(env, seed=0)
done = False
while not done:
    obs, r, term, trunc, info = env.step(agent.act(obs, info)); done = term or trunc
from selenv.fusion import ldmv_update
P = np.diag([1.0, 2.0, 3.0, 1.0, 1.0, 1.0, 0.1, 0.1, 0.1]); H = np.zeros((1, 9)); H[0, 0] = 1.0
res = ldmv_update(P, 2 * P, H, -H, np.array([[0.01]]))
assert np.all(np.isfinite(res.P)) and np.all(np.linalg.eigvalsh(res.P) > 0)
env = gym.make("selenv/CLScheduling-v1", fusion="ldmv"); obs, info = env.reset(seed=1)
env.step(int(np.flatnonzero(info["action_mask"])[0]))
print("OK", info["objective"])
""".replace("VENV", str(venv))
    out = _run([py, "-c", code], cwd=work, env=_env())
    assert out.startswith("OK")
    selenv_cmd = str(venv / "bin" / "selenv")
    out = _run(
        [
            selenv_cmd,
            "bench",
            "selenv/FIMSelection-v1",
            "--agents",
            "greedy,ppo",
            "--episodes",
            "2",
            "--no-progress",
            "--json",
            "r.json",
        ],
        cwd=work,
        env=_env(),
    )
    assert "ppo" in out and (work / "r.json").is_file()
    assert not list(work.glob("checkpoints*"))
