"""The models' one speed switch (networks.small_batch_convs, docs/reference/model.md "Speed and the CPU budget", docs/experiments/speed_levers.md): oneDNN
off only where it was measured to pay, through the public flag, restored on exit."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import torch

from embodied_tactile.model.networks import SMALL_BATCH_ONEDNN_OFF, small_batch_convs

SRC = Path(__file__).resolve().parents[2] / "src" / "embodied_tactile"

needs_onednn = pytest.mark.skipif(not torch.backends.mkldnn.is_available(), reason="torch built without oneDNN")


@needs_onednn
def test_onednn_off_only_up_to_the_measured_batch_and_restored():
    assert torch.backends.mkldnn.enabled
    for n in range(1, SMALL_BATCH_ONEDNN_OFF + 1):
        with small_batch_convs(n):
            assert not torch.backends.mkldnn.enabled, n
        assert torch.backends.mkldnn.enabled, n
    for n in (SMALL_BATCH_ONEDNN_OFF + 1, 8, 64):  # batch 8 was measured 0.81x with oneDNN off
        with small_batch_convs(n):
            assert torch.backends.mkldnn.enabled, n
    with pytest.raises(RuntimeError):  # restored on an error too
        with small_batch_convs(1):
            raise RuntimeError("boom")
    assert torch.backends.mkldnn.enabled


@needs_onednn
def test_a_user_setting_oneDNN_off_keeps_it_off():
    torch.backends.mkldnn.enabled = False
    try:
        with small_batch_convs(1):
            assert not torch.backends.mkldnn.enabled
        assert not torch.backends.mkldnn.enabled
    finally:
        torch.backends.mkldnn.enabled = True


def test_filter_step_gives_the_same_posterior_with_and_without_the_switch():
    from embodied_tactile.model import LatentFilter

    torch.manual_seed(0)
    m = LatentFilter("multi_l").eval()
    obs, act = torch.rand(1, 3, 28, 28), torch.randn(1, 6)
    with torch.no_grad():
        out, _ = m.filter_step(obs, act)  # the switch: oneDNN off at batch 1
        ref, _ = m.step(*m.encode(obs), act, None, False)  # oneDNN as configured
    for k in ("z_mean", "z_var", "y_mean", "y_var"):
        torch.testing.assert_close(out[k], ref[k], rtol=1e-5, atol=1e-6)


def test_no_private_torch_api_in_the_package():
    """torch._C and other underscore torch attributes stay out of the code (public flags only)."""
    hits = [f"{p.relative_to(SRC)}:{i}: {line.strip()}" for p in SRC.rglob("*.py")
            for i, line in enumerate(p.read_text().splitlines(), 1)
            if re.search(r"\btorch\._[A-Za-z]", line) and not line.lstrip().startswith("#")]
    assert not hits, hits


def test_infer_latents_skips_the_decoders_with_the_same_latents():
    from embodied_tactile.model import LatentFilter

    torch.manual_seed(0)
    m = LatentFilter("multi_l").eval()
    obs, act = torch.rand(2, 5, 3, 28, 28), torch.randn(2, 5, 6)
    calls = []
    for dec in m.observation.decoders.values():
        dec.register_forward_hook(lambda *a: calls.append(1))
    with torch.no_grad():
        full = m.forward(obs, act, sample=False)
    assert len(calls) == 2 and full["recon"].shape == (2, 5, 3, 28, 28)
    calls.clear()
    lat = m.infer_latents({"obs": obs, "actions": act})
    assert calls == []  # no decoder ran
    for k in ("z_mean", "z_var", "y_mean", "y_var"):
        torch.testing.assert_close(lat[k], full[k], rtol=0, atol=0)
    assert "recon" not in m.forward(obs, act, sample=False, decode=False)


def test_compile_convs_switch_counts_nets_and_leaves_eval_eager():
    import copy

    from embodied_tactile.model import LatentFilter
    from embodied_tactile.model.networks import ConvDecoder, ConvEncoder, compile_convs

    m = LatentFilter("multi_l")
    assert compile_convs(m) == 4  # two pathways x (encoder, decoder)
    nets = [mod for mod in m.modules() if getattr(mod, "compiled", False)]
    assert len(nets) == 4
    m.eval()
    with torch.no_grad():
        m.infer_latents({"obs": torch.rand(1, 3, 3, 28, 28), "actions": torch.randn(1, 3, 6)})
    assert all("_compiled_body" not in n.__dict__ for n in nets)  # eval / no grad: never compiled
    copied = [n for n in copy.deepcopy(m).modules() if isinstance(n, (ConvEncoder, ConvDecoder))]
    assert len(copied) == 4 and all(n.compiled for n in copied)  # the switch survives a copy
    assert compile_convs(m, False) == 4 and not any(n.compiled for n in nets)


def test_train_config_switch_compile_convs():
    from omegaconf import OmegaConf

    from embodied_tactile.run import runtime
    from embodied_tactile.model import LatentFilter

    root = Path(__file__).resolve().parents[2]
    assert OmegaConf.load(root / "configs" / "train.yaml").compile_convs is False  # the measured default
    m = LatentFilter("fsr_tb")
    assert runtime.configure_compile(OmegaConf.create({"compile_convs": False}), m) == 0
    assert not any(getattr(n, "compiled", False) for n in m.modules())
    assert runtime.configure_compile(OmegaConf.create({"compile_convs": True}), m) == 2


def test_no_grad_passes_run_the_convs_in_chunks_with_the_same_result(monkeypatch):
    from embodied_tactile.model import LatentFilter, networks

    torch.manual_seed(0)
    m = LatentFilter("fsr_tb").eval()
    obs, act = torch.rand(3, 40, 2, 28, 28), torch.randn(3, 40, 6)
    with torch.no_grad():
        whole = m.forward(obs, act, sample=False)  # 120 frames <= 1024: one call
        monkeypatch.setattr(networks, "CONV_CHUNK_FRAMES", 50)
        calls = []
        net = next(n for n in m.modules() if isinstance(n, networks.ConvEncoder))
        net.conv.register_forward_hook(lambda *a: calls.append(a[1][0].shape[0]))
        chunked = m.forward(obs, act, sample=False)
    assert calls == [50, 50, 20]
    for k in ("z_mean", "z_var", "y_mean", "recon"):
        torch.testing.assert_close(chunked[k], whole[k], rtol=1e-5, atol=1e-5)


def test_training_passes_run_the_convs_in_chunks_with_the_same_loss_and_gradients(monkeypatch):
    """Autograd passes over more than CONV_CHUNK_FRAMES frames are chunked too: the same
    ELBO terms and the same gradients (summed over chunks) as one call over every frame."""
    from embodied_tactile.model import LatentFilter, networks

    torch.manual_seed(0)
    m = LatentFilter("multi_l", obs_sigma=0.1, obs_dropout=0.0)  # the same frames observed in both passes
    batch = {"obs": torch.rand(3, 40, 3, 28, 28), "actions": torch.randn(3, 40, 6),
             "object_id": torch.tensor([0, 5, 9])}

    def loss_and_grads():
        m.zero_grad()
        t = m.elbo_terms(batch, sample=False)
        (t["nll"] + t["kl_z"] + t["kl_y"]).backward()
        return t["nll"].detach(), {n: p.grad.clone() for n, p in m.named_parameters() if p.grad is not None}

    nll_whole, g_whole = loss_and_grads()  # 120 frames <= 1024: one call
    monkeypatch.setattr(networks, "CONV_CHUNK_FRAMES", 50)
    calls = []
    enc = next(n for n in m.modules() if isinstance(n, networks.ConvEncoder))
    enc.conv.register_forward_hook(lambda *a: calls.append(a[1][0].shape[0]))
    nll_chunked, g_chunked = loss_and_grads()
    assert calls == [50, 50, 20]
    torch.testing.assert_close(nll_chunked, nll_whole, rtol=1e-5, atol=1e-3)
    assert g_chunked.keys() == g_whole.keys() and len(g_whole) > 10
    for name, g in g_whole.items():
        torch.testing.assert_close(g_chunked[name], g, rtol=1e-4, atol=1e-4, msg=name)
