"""The README's Python API examples run as written (one session, in order, in an empty folder).

Each block's claims are checked after it runs: shapes, the accurate default's renderer, the
fit's recovery of the rendered truth within its Laplace sigma, the RESULT.json round trip.
"""
from __future__ import annotations

import re
from pathlib import Path

import torch

README = Path(__file__).resolve().parents[1] / "README.md"


def python_blocks() -> list[str]:
    section = README.read_text().split("## Python API", 1)[1].split("\n## ", 1)[0]
    return re.findall(r"```python\n(.*?)```", section, flags=re.S)


def test_readme_has_the_api_examples():
    code = "\n".join(python_blocks())
    for call in ("skyfit.render(", "skyfit.fit(", "skyfit.sample(", "skyfit.export_luts(", "Observation.from_arrays(",
                 "skyfit.load_result(", ".save("):
        assert call in code, call


def test_readme_python_api_runs(tmp_path, monkeypatch, one_thread):
    monkeypatch.chdir(tmp_path)
    ns: dict = {}
    for block in python_blocks():
        exec(compile(block, str(README), "exec"), ns)  # noqa: S102  (our own README)
    atm, sky, result = ns["atm"], ns["sky"], ns["result"]
    assert sky.radiance.shape == (32, 32, 6) and sky.model["name"] == "gauss"
    # the fast setting is another measured renderer, close to the accurate one (mean ΔE <= 1 measured)
    valid = sky.valid
    rel = float((ns["fast"].radiance - sky.radiance)[valid].norm() / sky.radiance[valid].norm())
    assert 0 < rel < 0.05
    assert ns["zenith"].radiance.shape == (2, 6) and bool((ns["zenith"].radiance > 0).all())
    # the fit recovers the atmosphere it was rendered with (the fit's Chapman renderer differs from the
    # render's Gauss quadrature by ~1e-3, so allow a few sigma plus that model error)
    truth_g = float(atm.mie_g.mean())
    assert abs(result.parameters["mie_g"] - truth_g) < 0.01
    assert result.sigma["mie_g"] > 0
    assert abs(result.parameters["exposure"] - 1.0) < 0.01
    again = ns["again"]
    assert again.parameters == result.parameters and again.free == result.free
    torch.testing.assert_close(again.atmosphere().mie_extinction, result.atmosphere().mie_extinction)
    assert (tmp_path / "result.json").is_file()
    post = ns["posterior"]["parameters"]["mie_g"]
    assert post["p16"] <= post["median"] <= post["p84"]
    assert abs(post["median"] - result.parameters["mie_g"]) < 10 * result.sigma["mie_g"] + 1e-3
    assert ns["tables"].multiple.shape[:4] == (8, 16, 8, 4)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.json"]  # nothing else written
