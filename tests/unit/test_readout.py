"""The read-out over interaction time (``alignment.readout``): what it promises.

Before evidence arrives an estimate reads as the population's (NMSE about 1), a latent that
converges to the truth reads a curve that does not rise, and an untrained network's latents,
which drift over time without carrying the factors, read about 1 at every frame.
"""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest

from embodied_tactile.eval.krr import TimeResolvedAlignment, alignment_kwargs, fit_alignment, time_spans
from embodied_tactile.eval.metrics import nmse_over_time
from embodied_tactile.eval.results import evaluate_latents, first_below
from embodied_tactile.options.alignment import AlignmentOptions, alignment_options

FAST = dict(cv=3, alphas=(1e-2, 1.0, 100.0), gammas=(0.3, 1.0), n_threads=1)


def _factors(rng, n):
    return rng.uniform(-1.0, 1.0, (n, 4))


def _curve(train_lat, train_f, test_lat, test_f, **kw):
    align = fit_alignment(train_lat, train_f, **{**FAST, **kw})
    return nmse_over_time(test_f, align.predict(test_lat)).mean(axis=1), align


def test_time_spans_cover_every_frame_once():
    for n, b in ((300, 10), (50, 10), (7, 10), (123, 4), (1, 10)):
        spans = time_spans(n, b)
        covered = np.concatenate([np.arange(a, c) for a, c in spans])
        assert covered.tolist() == list(range(n))
        assert spans[0] == (0, 1) and max(c - a for a, c in spans) <= np.ceil(n / b)
    assert time_spans(300, 10)[-1] == (270, 300)  # the last span is the final tenth
    lengths = [c - a for a, c in time_spans(300, 10)]
    assert lengths[:5] == [1, 1, 2, 4, 8]  # short where a filter's posterior moves fastest


def test_constant_latent_reads_the_mean_at_every_frame():
    """A latent equal for every sequence at every frame carries nothing: about 1 everywhere."""
    rng = np.random.default_rng(0)
    f_tr, f_te = _factors(rng, 80), _factors(rng, 40)
    lat_tr, lat_te = np.ones((80, 30, 3)), np.ones((40, 30, 3))
    for readout in ("per_time", "final_segment"):
        curve, _ = _curve(lat_tr, f_tr, lat_te, f_te, readout=readout)
        assert np.all((curve > 0.9) & (curve < 1.15)), (readout, curve)


@pytest.mark.slow
def test_converging_latent_reads_a_curve_that_does_not_rise():
    """Latent = a smooth function of the factors plus noise that shrinks over the trial."""
    rng = np.random.default_rng(1)
    w = rng.normal(size=(4, 6))
    t = 40
    sigma = np.linspace(2.0, 0.02, t)[None, :, None]

    def split(n):
        f = _factors(rng, n)
        return np.tanh(f @ w)[:, None, :] + sigma * rng.normal(size=(n, t, 6)), f

    (lat_tr, f_tr), (lat_te, f_te) = split(160), split(80)
    curve, align = _curve(lat_tr, f_tr, lat_te, f_te)
    assert isinstance(align, TimeResolvedAlignment)
    assert 0.85 < curve[0] < 1.2 and curve[-1] < 0.1
    # non-increasing at the read-out's resolution (a span's frames share one probe; single
    # frames of 80 test sequences scatter by a few hundredths)
    by_span = np.array([curve[a:b].mean() for a, b in time_spans(t, align.time_bins)])
    assert np.all(np.diff(by_span) <= 0.02), np.round(by_span, 3)
    assert first_below(curve, 0.5) is not None and first_below(np.ones(5), 0.5) is None


@pytest.mark.slow
def test_a_latent_the_final_segment_never_saw_reads_no_worse_than_the_mean():
    """Early latents far from the final ones (a drift the final-tenth fit never saw) read about
    1 with the per-time read-out, and its last frame is the paper protocol's."""
    rng = np.random.default_rng(2)
    t = 40
    drift = np.linspace(6.0, 0.0, t)[None, :, None]

    def split(n):
        f = _factors(rng, n)
        informative = np.linspace(0.0, 1.0, t)[None, :, None] * f[:, None, :2]
        return np.concatenate([informative, np.zeros((n, t, 1))], axis=2) + drift + 0.05 * rng.normal(size=(n, t, 3)), f

    (lat_tr, f_tr), (lat_te, f_te) = split(120), split(60)
    per_time, _ = _curve(lat_tr, f_tr, lat_te, f_te, readout="per_time")
    paper, _ = _curve(lat_tr, f_tr, lat_te, f_te, readout="final_segment")
    assert per_time.max() < 1.2 and 0.9 < per_time[0] < 1.2, np.round(per_time, 2)
    assert abs(per_time[-1] - paper[-1]) < 0.05  # the last span is the final tenth: same last frame


def test_untrained_network_reads_about_one_at_every_frame():
    """An untrained Latent Filter's y drifts through its random recursion; on observations that
    carry no factor its curve stays near 1 at every frame."""
    torch = pytest.importorskip("torch")
    from embodied_tactile.model.latent_filter import LatentFilter

    torch.manual_seed(0)
    torch.set_num_threads(1)
    net = LatentFilter("acc", n_z=2, n_y=4, n_a=6, encoder={"widths": [2, 2], "hidden": 8},
                       transition_hidden=8, lstm_hidden=4).eval()
    g = torch.Generator().manual_seed(3)
    rng = np.random.default_rng(3)

    def split(n):
        obs, acts = torch.rand(n, 30, 1, 28, 28, generator=g), torch.randn(n, 30, 6, generator=g)
        with torch.no_grad():
            y = net.infer_latents(obs, acts)["y_mean"].numpy()
        return y, _factors(rng, n)

    (y_tr, f_tr), (y_te, f_te) = split(90), split(45)
    assert np.abs(y_tr[:, 0] - y_tr[:, -1]).mean() > 1e-3  # the latents do move over the trial
    curve, _ = _curve(y_tr, f_tr, y_te, f_te)
    assert 0.9 <= curve[0] <= 1.2 and np.all(curve <= 1.2), np.round(curve, 3)


def test_options_have_one_default_and_refuse_unknown_keys():
    assert alignment_options().readout == AlignmentOptions.readout
    built = alignment_options({"readout": "final_segment"}, None, {"cv": 2})
    assert isinstance(built, AlignmentOptions) and (built.readout, built.cv) == ("final_segment", 2)
    assert alignment_options(built, {"seed": 3}) == dataclasses.replace(built, seed=3)  # a typed layer
    with pytest.raises(ValueError, match="unknown alignment option"):
        alignment_options({"final_segmnet": 0.2})
    for bad, message in (({"readout": "per_frame"}, "alignment.readout='per_frame' (str): expected one of per_time, final_segment"),
                         ({"cv": 1}, "alignment.cv=1 (int): expected an integer >= 2"),
                         ({"time_bins": 0}, "alignment.time_bins=0 (int): expected an integer >= 1")):
        with pytest.raises(ValueError, match=re.escape(message)):
            alignment_options(bad)


def test_the_read_out_takes_the_options_typed():
    with pytest.raises(TypeError, match="takes an AlignmentOptions"):
        alignment_kwargs({"cv": 2}, "trial", None)
    assert alignment_kwargs(alignment_options({"groups": "auto"}), "trial", None)["groups"] is None


def test_evaluate_latents_reports_the_curve_and_its_first_frame_below_half():
    rng = np.random.default_rng(4)
    w = rng.normal(size=(4, 5))
    t = 20

    def split(n, offset):
        f = _factors(rng, n)
        conv = np.linspace(0.0, 1.0, t)[None, :, None]
        lat = np.tanh(f @ w)[:, None, :] * conv + 0.02 * rng.normal(size=(n, t, 5))
        return {"y": lat, "factors": f, "object_id": np.arange(n) % 32, "action_index": np.zeros(n, int),
                "seq_id": np.arange(n) + offset}

    res, _ = evaluate_latents(split(100, 0), split(40, 1000), alignment=alignment_options(FAST))
    s = res.summary()
    assert len(s["nmse_curve_overall"]) == t
    assert s["nmse_curve_overall"][-1] == pytest.approx(s["nmse_last_step_overall"])
    k = s["first_frame_below_half"]
    assert k is not None and s["nmse_curve_overall"][k] <= 0.5 and all(v > 0.5 for v in s["nmse_curve_overall"][:k])


def test_the_callbacks_latent_choices_are_the_readers_latents():
    from dataclasses import fields

    from embodied_tactile.eval.latents import LATENT_KEYS
    from embodied_tactile.options.alignment import AlignmentCheckOptions

    latent = next(f for f in fields(AlignmentCheckOptions) if f.name == "latent")
    assert set(latent.metadata["choices"]) == set(LATENT_KEYS)
