"""run.provenance: what provenance.json says of the machine a run computed on."""

import json
import sys

import pytest
from omegaconf import OmegaConf


def test_provenance_names_the_cpu_model_the_cores_and_torchs_kernel_level(tmp_path):
    from embodied_tactile.run.provenance import save_provenance

    save_provenance(OmegaConf.create({"seed": 0}), tmp_path)
    cpu = json.loads((tmp_path / "provenance.json").read_text())["cpu"]
    assert set(cpu) == {"model", "cores", "torch_capability"}
    assert 1 <= cpu["cores"] and cpu["torch_capability"] in ("DEFAULT", "AVX2", "AVX512", "ZVECTOR", "SVE256")
    if sys.platform.startswith("linux"):
        with open("/proc/cpuinfo") as f:
            names = {line.split(":", 1)[1].strip() for line in f if line.startswith("model name")}
        assert cpu["model"] in names


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/cpuinfo is Linux's")
def test_the_cpu_model_falls_back_when_cpuinfo_has_none(monkeypatch):
    from embodied_tactile.run import provenance

    monkeypatch.setattr(provenance.platform, "processor", lambda: "x86_64")
    real = provenance.Path.read_text
    monkeypatch.setattr(provenance.Path, "read_text",
                        lambda self, *a, **k: "processor\t: 0\n" if str(self) == "/proc/cpuinfo" else real(self, *a, **k))
    assert provenance.cpu()["model"] == "x86_64"
