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

    from embodied_tactile.run.compile_convs import configure_compile
    from embodied_tactile.model import LatentFilter

    root = Path(__file__).resolve().parents[2]
    assert OmegaConf.load(root / "configs" / "train.yaml").compile_convs is False  # the measured default
    m = LatentFilter("fsr_tb")
    assert configure_compile(OmegaConf.create({"compile_convs": False}), m) == 0
    assert not any(getattr(n, "compiled", False) for n in m.modules())
    assert configure_compile(OmegaConf.create({"compile_convs": True}), m) == 2


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


@pytest.mark.parametrize("c_in,c_out", [(16, 1), (16, 2), (3, 5)])
def test_subpixel_conv_transpose_equals_the_transposed_conv(c_in, c_out):
    """The decoder's last layer as one 3x3 conv and a pixel shuffle: the same output and
    the same gradients (input, weight, bias) as F.conv_transpose2d, up to float rounding."""
    from torch.nn import functional as F

    from embodied_tactile.model.networks import subpixel_conv_transpose

    torch.manual_seed(0)
    x = torch.randn(4, c_in, 14, 14, requires_grad=True)
    w = torch.randn(c_in, c_out, 4, 4, requires_grad=True)
    b = torch.randn(c_out, requires_grad=True)
    g = torch.randn(4, c_out, 28, 28)
    outs = []
    for fn in (lambda: F.conv_transpose2d(x, w, b, stride=2, padding=1), lambda: subpixel_conv_transpose(x, w, b)):
        y = fn()
        grads = torch.autograd.grad(y, (x, w, b), g)
        outs.append((y, *grads))
    for ref, new in zip(*outs):  # the bias gradient sums 4 x 784 terms per batch row: rtol 1e-4
        torch.testing.assert_close(new, ref, rtol=1e-4, atol=1e-5)


def _decoder_reference(dec, z):
    """ConvDecoder.body before the sub-pixel layer (the reference computation)."""
    h = dec.fc(z).view(z.shape[0], dec.w2, 7, 7).contiguous(memory_format=torch.channels_last)
    return dec.deconv(h)


def test_training_step_equals_the_reference_computation(monkeypatch):
    """A training loss and its gradients on a fixed batch of >= CHANNELS_LAST_MIN_FRAMES
    frames: the sub-pixel last layer, the contiguous means and the per-frame likelihood
    sum give the reference's (the elementwise likelihood, the transposed conv) to float
    rounding (the loss to ~1e-6 relative)."""
    from embodied_tactile.model import LatentFilter, latent_filter, networks

    torch.manual_seed(0)
    m = LatentFilter("multi_l", obs_sigma=0.1, obs_dropout=0.0, encoder={"widths": [4, 8], "hidden": 16})
    batch = {"obs": torch.rand(2, 40, 3, 28, 28), "actions": torch.randn(2, 40, 6),
             "object_id": torch.tensor([0, 5])}
    assert 80 >= networks.CHANNELS_LAST_MIN_FRAMES

    def loss_and_grads():
        m.zero_grad()
        torch.manual_seed(1)  # the same draws in both passes
        t = m.elbo_terms(batch, sample=True)
        loss = t["nll"] + t["kl_z"] + t["kl_y"]
        loss.backward()
        grads = {n: p.grad.clone() for n, p in m.named_parameters() if p.grad is not None}
        return loss.detach(), grads, t["out"]["recon"].is_contiguous()

    loss_new, g_new, contiguous = loss_and_grads()
    assert contiguous  # the means in the observations' layout
    monkeypatch.setattr(networks.ConvDecoder, "body", _decoder_reference)
    monkeypatch.setattr(latent_filter, "gaussian_nll_frames", lambda x, mean, ls: networks.gaussian_nll(
        x, mean, ls.view(-1, 1, 1)).sum(dim=(-3, -2, -1)))
    loss_ref, g_ref, _ = loss_and_grads()
    assert abs(float(loss_new) - float(loss_ref)) <= 1e-6 * abs(float(loss_ref)) + 1e-4
    assert g_new.keys() == g_ref.keys() and len(g_ref) > 10
    for name, g in g_ref.items():  # relative to each gradient's largest entry (measured <= 2e-6)
        assert float((g_new[name] - g).abs().max()) <= 1e-5 * float(g.abs().max()), name


def test_frame_likelihood_equals_the_elementwise_sum():
    """gaussian_nll_frames: the per-frame sum of gaussian_nll, its value and gradients to
    float rounding."""
    from embodied_tactile.model.networks import gaussian_nll, gaussian_nll_frames

    torch.manual_seed(0)
    x = torch.rand(3, 7, 3, 28, 28)
    mean = torch.rand(3, 7, 3, 28, 28, requires_grad=True)
    ls = torch.tensor([-2.3, -1.0, 0.2], requires_grad=True)
    ref = gaussian_nll(x, mean, ls.view(-1, 1, 1)).sum(dim=(-3, -2, -1))
    new = gaussian_nll_frames(x, mean, ls)
    assert new.shape == (3, 7)
    torch.testing.assert_close(new, ref, rtol=1e-6, atol=1e-3)
    g_ref = torch.autograd.grad(ref.sum(), (mean, ls))
    g_new = torch.autograd.grad(new.sum(), (mean, ls))
    for a, b in zip(g_new, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-4)


def test_the_input_check_reads_a_finite_sum_as_finite_inputs_and_still_names_bad_frames():
    from embodied_tactile.model.module import nonfinite_inputs

    big = {"obs": torch.full((2, 3, 1, 28, 28), 3e38), "actions": torch.zeros(2, 3, 6)}  # finite; the sum overflows
    assert not torch.isfinite(big["obs"].sum()) and nonfinite_inputs(big) == []
    bad = {"obs": torch.rand(2, 3, 1, 28, 28), "actions": torch.zeros(2, 3, 6)}
    assert nonfinite_inputs(bad) == []
    bad["obs"][1, 2, 0, 5, 5] = float("nan")
    assert nonfinite_inputs(bad) == ["batch row 1 obs frame 2"]
