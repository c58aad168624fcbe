"""One device check for envs, fits and benchmarks: cpu and cuda[:N] where torch can use it, else a ValueError."""

from __future__ import annotations

import pytest
import torch

from redsim import pretrained
from redsim.devices import check_device
from redsim.trainers.fit import FitConfig, FitConfigError


def test_cpu_passes_and_devices_redsim_cannot_use_are_refused() -> None:
    assert check_device("cpu") == "cpu" and check_device(torch.device("cpu")) == "cpu"
    for bad in ("meta", "mps", "bogus", None, 1.5):
        with pytest.raises(ValueError, match=r"device must be 'cpu' or 'cuda\[:N\]'"):
            check_device(bad)
    missing = f"cuda:{torch.cuda.device_count()}"  # one index past the last GPU (cuda:0 without one)
    with pytest.raises(ValueError, match="is not available"):
        check_device(missing)
    with pytest.raises(FitConfigError, match="device"):
        FitConfig(device="mps")


def test_bench_refuses_a_device_it_cannot_use(cli) -> None:
    code, _, err = cli("bench", "energy", "--scenes", "mini_chain", "--device", "meta")
    assert code == 2 and "--device: device must be 'cpu' or 'cuda[:N]'" in err


def test_loading_a_map_onto_a_device_it_cannot_use_names_the_device() -> None:
    """torch.load's error for it (map_location="cuda" on a CPU-only torch, or "bogus") was reported as a
    CheckpointError "weights are corrupt or truncated", of shipped weights that are not."""
    for bad in ("bogus", f"cuda:{torch.cuda.device_count()}"):
        with pytest.raises(ValueError, match="device") as error:
            pretrained.load("mini_chain", device=bad)
        assert "corrupt" not in str(error.value)
