"""What a run folder records about where its run came from: ``provenance.json`` (git
commit, dirty flag and diff, package versions, command line, host and CPU), ``config_resolved.yaml``,
the identity of the data it was trained on (per cache file and per trial, which a resume and
evaluate.py compare with) and the process's peak memory."""

from __future__ import annotations

import importlib.metadata as md
import json
import os
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

from omegaconf import DictConfig, OmegaConf

from embodied_tactile.jsonio import write_json

#: the packages whose versions provenance.json records
PACKAGES = (
    "embodied-tactile", "torch", "lightning", "hydra-core", "omegaconf", "torchmetrics", "librosa",
    "h5py", "numpy", "scipy", "scikit-learn", "wandb", "pyserial", "umap-learn",
)


def package_versions() -> dict[str, str | None]:
    out: dict[str, str | None] = {}
    for name in PACKAGES:
        try:
            out[name] = md.version(name)
        except md.PackageNotFoundError:
            out[name] = None
    return out


def cpu() -> dict[str, Any]:
    """The CPU a run computed on: its model name (``/proc/cpuinfo``; ``platform.processor()``
    elsewhere), the cores this process may use and torch's kernel level. At the same thread
    count the same CPU model trains to the same last digit, another model does not
    (docs/experiments/variance_components.md, "The main job on another CPU")."""
    import torch

    from embodied_tactile.run.threads import available_cores

    model = None
    try:
        model = next((line.split(":", 1)[1].strip() for line in Path("/proc/cpuinfo").read_text().splitlines()
                      if line.startswith("model name")), None)
    except OSError:
        pass
    return {"model": model or platform.processor() or None, "cores": available_cores(),
            "torch_capability": torch.backends.cpu.get_cpu_capability()}


def git_state(repo: str | os.PathLike | None = None) -> dict[str, Any]:
    """Commit, dirty flag and diff of the source tree (None where git is unavailable)."""
    repo = Path(repo or Path(__file__).resolve().parents[3])

    def git(*args: str) -> str | None:
        try:
            return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, timeout=10, check=True).stdout
        except (OSError, subprocess.SubprocessError):
            return None

    commit = git("rev-parse", "HEAD")
    diff = git("diff", "HEAD")
    return {"commit": commit.strip() if commit else None, "dirty": bool(diff), "diff": diff or ""}


def save_provenance(cfg: DictConfig, run_dir: str | os.PathLike) -> None:
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config_resolved.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
    git = git_state()
    if git["diff"]:
        (run_dir / "git.diff").write_text(git["diff"])
    write_json(
        run_dir / "provenance.json",
        {
            "git_commit": git["commit"],
            "git_dirty": git["dirty"],
            "packages": package_versions(),
            "python": sys.version,
            "platform": platform.platform(),
            "cpu": cpu(),
            "argv": sys.argv,
            "cwd": os.getcwd(),
            "started": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        },
    )


def data_identity(cache_files: Mapping[str, str | os.PathLike],
                  trial_digests: Mapping[str, Mapping[str, str]] | None = None,
                  trials: Sequence[str] | None = None) -> dict[str, Any]:
    """What the run's data were: per field, the raw files and the digests of their stored
    bytes and trial attributes that the preparation stage computed when it built or found
    the cache (its root attrs ``sources`` / ``source_digests``; nothing is hashed again),
    and, given the preparation's ``trial_digests``, ``trials``: ``{trial: digest}`` of each
    of ``trials`` (all when None), so that a change is named per trial and trials the run
    never used do not count."""
    from embodied_tactile.data.cache import cache_info

    out: dict[str, Any] = {}
    for field, path in sorted(cache_files.items()):
        info = cache_info(path)
        out[field] = {"raw_files": [str(p) for p in info.get("sources", [])],
                      "digests": list(info.get("source_digests", []))}
        if trial_digests and field in trial_digests:
            per = trial_digests[field]
            out[field]["trials"] = {n: per[n] for n in sorted(per if trials is None else trials) if n in per}
    return out


def trial_digests(datamodule: Any) -> dict[str, dict[str, str]] | None:
    """The preparation stage's per-trial digests of a DataModule (None when it has none)."""
    prepared = getattr(datamodule, "prepared", None)
    return getattr(prepared, "trial_digests", None) or None


def data_changes(saved: Mapping[str, Any] | None, now: Mapping[str, Any]) -> list[str]:
    """How the data differ from those a run was trained on (``provenance.json``
    ``raw_data`` against :func:`data_identity` now): with per-trial digests on both sides,
    one line per trial of the run that is gone or whose data or attributes changed (other
    trials of the raw files do not count); else one line per raw file and field whose
    digest differs, a field missing, or a different number of raw files. [] when the same."""
    if not saved:
        return []
    out = []
    for field in sorted(set(saved) | set(now)):
        a, b = saved.get(field), now.get(field)
        if a is None or b is None:
            out.append(f"field {field}: {'not prepared now' if b is None else 'not in the training data'}")
            continue
        if "trials" in a and "trials" in b:
            for name, da in sorted(a["trials"].items()):
                db = b["trials"].get(name)
                if db is None:
                    out.append(f"trial {name}: not in the data now ({', '.join(b['raw_files'])})")
                elif db != da:
                    out.append(f"trial {name}: its {field} data or attributes changed since training "
                               f"(digest {da[:12]} -> {db[:12]}; {', '.join(b['raw_files'])})")
            continue
        if len(a["digests"]) != len(b["digests"]):
            out.append(f"field {field}: {len(a['digests'])} raw file(s) at training, {len(b['digests'])} now "
                       f"({', '.join(b['raw_files'])})")
            continue
        for i, (da, db) in enumerate(zip(a["digests"], b["digests"])):
            if da != db:
                path = b["raw_files"][i] if i < len(b["raw_files"]) else "?"
                out.append(f"{path}: its trials or their {field} data changed since training (digest {da[:12]} -> {db[:12]})")
    return out


def record_data_identity(run_dir: str | os.PathLike, cache_files: Mapping[str, str | os.PathLike],
                         trial_digests: Mapping[str, Mapping[str, str]] | None = None,
                         trials: Sequence[str] | None = None) -> None:
    """Add :func:`data_identity` (per trial of ``trials``, the run's split, when the
    preparation's ``trial_digests`` are given) to ``provenance.json`` as ``raw_data``."""
    path = Path(run_dir) / "provenance.json"
    prov = json.loads(path.read_text()) if path.is_file() else {}
    prov["raw_data"] = data_identity(cache_files, trial_digests, trials)
    write_json(path, prov)


def peak_rss_bytes() -> int:
    """Peak resident memory of this process and its finished children (Linux: KiB units)."""
    own = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    children = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return int(max(own, children) * 1024)


__all__ = ["PACKAGES", "data_changes", "data_identity", "git_state", "package_versions", "peak_rss_bytes", "record_data_identity", "save_provenance", "trial_digests"]
