"""Every example runs and passes its own check() (with the tiny budget of its main()'s defaults)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

EXAMPLES = sorted((Path(__file__).parent.parent / "examples").glob("*.py"))
if not EXAMPLES:  # the tests copied beside an installed wheel
    pytest.skip("needs the source checkout (examples/)", allow_module_level=True)
OPTIONAL = {"rllib_agent": ("ray", 'Ray RLlib is not installed (pip install "redsim[ray]")')}
"""Examples that need an optional extra: example -> (module, why it is skipped without it)."""


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.stem for p in EXAMPLES])
def test_example_runs_and_checks(path: Path, tmp_path: Path) -> None:
    if path.stem in OPTIONAL:
        module_name, reason = OPTIONAL[path.stem]
        pytest.importorskip(module_name, reason=reason)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    module.check(module.main(tmp_path))
