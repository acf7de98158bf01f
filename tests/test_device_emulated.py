"""Every tensor op on "CUDA" without a GPU: the CLI's fits under an emulated device (tests/_fake_cuda.py).

CI has no GPU, and an H200 found four crashes after converged fits, each a CPU tensor meeting a CUDA one
(docs/benchmarks.md, section 9). The emulation raises where CUDA would; each command runs in a fresh process (the
emulation patches torch.cuda for its process). A planted mix must raise, so that a silent harness cannot pass.
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent


def _emulated(code: str, cwd: Path) -> subprocess.CompletedProcess:
    prog = "import sys; sys.path[:0] = [%r, %r]\nimport _fake_cuda; _fake_cuda.install()\n" % (str(TESTS), str(ROOT))
    return subprocess.run([sys.executable, "-c", prog + textwrap.dedent(code)], cwd=cwd, capture_output=True, text=True,
                          timeout=600, env={"OMP_NUM_THREADS": "1", "PATH": "/usr/bin:/bin", "MPLBACKEND": "Agg"})


def _cli(args: list, cwd: Path) -> subprocess.CompletedProcess:
    return _emulated(f"from skyfit.cli import main\nsys.exit(main({[str(a) for a in args]!r}))", cwd)


def test_the_emulation_refuses_what_cuda_refuses(tmp_path):
    p = _emulated("""
        import torch
        a = torch.zeros(3, device="cuda")
        assert a.device.type == "cuda" and torch.cuda.is_available()
        b = a + torch.ones(()) + torch.ones(3).to("cuda")      # a 0-dim CPU scalar and a moved tensor: allowed
        assert a[torch.tensor([0, 2])].shape == (2,)            # CPU indices into a CUDA tensor: allowed
        for bad in (lambda: a + torch.ones(3), lambda: torch.ones(3)[a > 0], lambda: a.numpy()):
            try:
                bad()
            except RuntimeError as e:
                assert "[fakecuda]" in str(e)
            else:
                raise SystemExit("not refused")
        print("ok")
    """, tmp_path)
    assert p.returncode == 0 and p.stdout.strip() == "ok", p.stderr[-2000:]


@pytest.fixture(scope="module")
def hg_sky(tmp_path_factory):
    """A 24 px render of earth with a one-term Henyey-Greenstein aerosol (the phase expansion's case) and its config."""
    import yaml

    from skyfit.atmosphere import load_yaml
    from skyfit.cli import main

    d = tmp_path_factory.mktemp("emulated")
    cfg = load_yaml(ROOT / "skyfit" / "configs" / "earth.yaml")
    cfg.setdefault("mie", {})["phase"] = "henyey_greenstein"
    (d / "hg.yaml").write_text(yaml.safe_dump(cfg))
    assert main([str(a) for a in ("render", d / "hg.yaml", "--out", d / "sky.exr", "--sun-zenith", "40", "--size", "24")]) == 0
    return d


def test_fit_with_the_whole_error_budget_and_evaluate_on_emulated_cuda(hg_sky):
    """``fit --laplace --sigma-phase`` (Laplace, numerical term, floor and sandwich, the two-term phase refit, the report's
    maps) and ``evaluate --refit-nuisance`` with ``--device cuda``: no device mix, and the CUDA-tagged fit writes what
    the CPU fit writes (the emulation computes on the CPU: equal to 1e-9)."""
    out = {}
    for dev in ("cuda", "cpu"):
        p = _cli(["fit", "sky.exr", "--config", "hg.yaml", "--free", "mie_beta_550,mie_g,exposure", "--laplace", "--sigma-phase",
                  "--no-progress", "--device", dev, "--out", f"{dev}.json"], hg_sky)
        assert p.returncode == 0, p.stderr[-3000:]
        out[dev] = json.loads((hg_sky / f"{dev}.json").read_text())
    assert out["cuda"]["laplace"]["budget"]["phase_expansion"] is not None  # the two-term refit ran (its shift: found here)
    for n in out["cpu"]["free"]:
        assert out["cuda"]["parameters"][n] == pytest.approx(out["cpu"]["parameters"][n], rel=1e-9)
        assert out["cuda"]["laplace"]["sigma"][n] == pytest.approx(out["cpu"]["laplace"]["sigma"][n], rel=1e-9)
    p = _cli(["evaluate", "cuda.json", "sky.exr", "--refit-nuisance", "--json", "--device", "cuda"], hg_sky)
    assert p.returncode == 0, p.stderr[-3000:]
    assert json.loads(p.stdout)["rmse"] >= 0
