"""docs/fitting.md's list of the config's ``fit:`` keys names every field of FitSettings, and nothing else."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

from skyfit.fit.problem import FitSettings

DOC = Path(__file__).resolve().parents[1] / "docs" / "fitting.md"


def test_fitting_md_lists_every_fit_setting():
    text = DOC.read_text()
    seg = text[text.index("holding any of: `"):text.index("` (the keys are the fields")]
    listed = set(re.findall(r"[a-z][a-z_0-9]*", seg)) - {"holding", "any", "of", "old", "name", "still", "read"}
    fields = {f.name for f in dataclasses.fields(FitSettings)}
    assert fields <= listed, sorted(fields - listed)
    assert listed - fields <= {"sun_disc_deg"}, sorted(listed - fields)  # the old name the parser still reads
