"""Evaluation library: NMSE, KRR alignment (leakage guards, Nystroem), baselines, tables, figures."""

from __future__ import annotations

import json
import os
import warnings
from pathlib import Path

import numpy as np
import pytest

from conftest import stable_seed


#: the GRU baseline on whole sequences and raw inputs (GRUOptions: evaluate.py's crops, standardised)
WHOLE = {"window": None, "windows_per_trial": 1, "input_standardize": False}


def _stable_seed(*parts) -> int:
    return stable_seed(repr(parts))

os.environ.setdefault("NUMBA_CACHE_DIR", str(Path(os.environ.get("TMPDIR", "/tmp")) / "embodied_tactile_numba"))

from embodied_tactile.constants import OBJECTS  # noqa: E402
from embodied_tactile.eval import (LeakageError, NMSE_DEFINITION, NMSEUndefinedWarning, Results,  # noqa: E402
                                   evaluate_latents, fit_alignment, nmse, nmse_over_time, nmse_trajectory, overall)
from embodied_tactile.eval.krr import final_segment_rows  # noqa: E402
from embodied_tactile.options.alignment import alignment_options  # noqa: E402


@pytest.fixture(autouse=True)
def _one_blas_thread():
    """The test machine is small and shared: multi-threaded BLAS only thrashes."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):
        yield


# ------------------------------------------------------------------ synthetic latents
def synthetic_split(n, *, t=40, d=16, seed=0, noise=0.05, offset=0, rng_w=1234):
    """Latents converge over time to a smooth nonlinear function of the factors."""
    rng = np.random.default_rng(seed)
    w = np.random.default_rng(rng_w).normal(size=(4, d))
    obj = rng.integers(0, 32, n)
    u = rng.uniform(-1, 1, (n, 4))  # latent causes
    factors = np.c_[np.sin(2 * u[:, 0]), u[:, 1] ** 3 + u[:, 1], np.exp(u[:, 2]), np.tanh(2 * u[:, 3])]
    base = np.tanh(u @ w)
    conv = (1 - np.exp(-np.arange(t) / 8.0))[None, :, None]
    lat = base[:, None, :] * conv + noise * rng.normal(size=(n, t, d))
    return {"y": lat, "z": lat[..., ::-1].copy(), "factors": factors, "object_id": obj,
            "action_index": rng.integers(0, 16, n), "seq_id": np.arange(n) + offset}


# ------------------------------------------------------------------ NMSE
def test_nmse_matches_hand_computation():
    y = np.array([[1.0, 0.0], [2.0, 1.0], [3.0, 2.0], [6.0, 1.0]])
    yh = np.array([[1.5, 0.0], [2.0, 0.5], [2.0, 2.0], [5.0, 1.0]])
    # factor 0: err = .25+0+1+1 = 2.25 ; mean = 3, den = 4+1+0+9 = 14
    # factor 1: err = 0+.25+0+0 = .25 ; mean = 1, den = 1+0+1+0 = 2
    np.testing.assert_allclose(nmse(y, yh), [2.25 / 14, 0.25 / 2])
    # trajectory form == flattening (sequence, frame)
    pred = np.stack([yh, y], axis=1)  # (4, 2, 2)
    np.testing.assert_allclose(nmse_trajectory(y, pred), [2.25 / 28, 0.25 / 4])
    np.testing.assert_allclose(nmse_over_time(y, pred), [[2.25 / 14, 0.25 / 2], [0.0, 0.0]])
    # NaN targets are ignored
    y2 = np.vstack([y, [[np.nan, np.nan]]])
    np.testing.assert_allclose(nmse(y2, np.vstack([yh, [[0.0, 0.0]]])), [2.25 / 14, 0.25 / 2])


def test_nmse_zero_variance_is_nan_with_warning():
    y = np.array([[1.0, 1.0], [2.0, 1.0], [3.0, 1.0]])
    with pytest.warns(NMSEUndefinedWarning):
        out = nmse(y, y + 0.1)
    assert np.isfinite(out[0]) and np.isnan(out[1])
    # with a reference variance the subset value is defined
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        out = nmse(y, y + 0.1, var_ref=np.array([1.0, 0.5]))
    np.testing.assert_allclose(out, [0.01, 0.02])


# ------------------------------------------------------------------ KRR
@pytest.mark.slow
def test_krr_recovers_smooth_nonlinear_mapping_and_not_shuffled():
    tr, te = synthetic_split(240, seed=1), synthetic_split(80, seed=2, offset=10_000)
    align = fit_alignment(tr["y"], tr["factors"], ids=tr["seq_id"], readout="final_segment")
    assert align.params["kernel"] == "rbf" and align.params["method"] == "exact_krr"
    pred = align.predict(te["y"], ids=te["seq_id"])
    assert pred.shape == (80, 40, 4)
    last = nmse(te["factors"], pred[:, -1])
    assert np.all(last < 0.05), last
    # early frames (unconverged latents) are worse than late ones
    curve = nmse_over_time(te["factors"], pred)
    assert curve[0].mean() > curve[-1].mean()
    # shuffled targets: nothing to learn -> about the mean predictor
    rng = np.random.default_rng(0)
    bad = fit_alignment(tr["y"], tr["factors"][rng.permutation(240)], readout="final_segment")
    assert np.all(nmse(te["factors"], bad.predict(te["y"])[:, -1]) > 0.8)


def test_alignment_never_scores_its_training_sequences():
    tr = synthetic_split(60, seed=3)
    align = fit_alignment(tr["y"], tr["factors"], ids=tr["seq_id"], cv=3)
    with pytest.raises(LeakageError):
        align.predict(tr["y"][:5], ids=tr["seq_id"][:5])
    te = synthetic_split(20, seed=4, offset=5)  # ids 5..24 overlap the training ids 0..59
    with pytest.raises(LeakageError):
        evaluate_latents(tr, te)


def test_cv_uses_training_rows_only(monkeypatch):
    """The grid search only ever sees the training rows; held-out latents enter predict only."""
    import embodied_tactile.eval.krr as krr

    tr, te = synthetic_split(50, seed=5), synthetic_split(30, seed=6, offset=1000)
    te["y"] = te["y"] + 100.0  # unmistakable held-out values
    seen = []
    orig = krr._grid_cv

    def spy(xs, ys, folds, *a, **k):
        seen.append((xs.copy(), folds))
        return orig(xs, ys, folds, *a, **k)

    monkeypatch.setattr(krr, "_grid_cv", spy)
    res, align = evaluate_latents(tr, te, alignment=alignment_options({"cv": 3, "frames_per_sequence": 2, "readout": "final_segment"}))
    (xs, folds), = seen
    assert xs.shape[0] == 50 * 2  # 2 final-segment frames per training sequence
    raw = xs * align.x_scale + align.x_mean
    assert np.abs(raw).max() < 50  # no held-out row (they are ~100)
    # folds are grouped by sequence: no sequence on both sides
    seq = np.repeat(np.arange(50), 2)
    for a, b in folds:
        assert not set(seq[a]) & set(seq[b])
    assert res.n_train == 50 and res.n_test == 30


def test_grid_cv_matches_sklearn_gridsearchcv():
    from sklearn.kernel_ridge import KernelRidge
    from sklearn.model_selection import GridSearchCV, GroupKFold

    from embodied_tactile.eval.krr import _grid_cv

    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(60, 3)), rng.normal(size=(60, 2))
    groups = np.repeat(np.arange(20), 3)
    folds = list(GroupKFold(3).split(x, y, groups))
    gammas, alphas = [0.1, 1.0], [1e-2, 1.0]
    ours = _grid_cv(x, y, folds, gammas, alphas, nystroem=False, m=0, seed=0)
    gs = GridSearchCV(KernelRidge(kernel="rbf"), {"gamma": gammas, "alpha": alphas}, cv=folds,
                      scoring="neg_mean_squared_error").fit(x, y)
    ref = -gs.cv_results_["mean_test_score"].reshape(2, 2).T  # sklearn orders params alphabetically: alpha, gamma
    np.testing.assert_allclose(ours, ref, rtol=1e-6)


def test_object_split_alignment_chooses_its_hyperparameters_on_unseen_objects():
    """Latents that code only object identity (a random point per object, unrelated to the
    factors): sequence-grouped CV, where every object sits on both sides of a fold, picks a
    memorising fit that is worse than the mean on unseen objects; the object split's 'auto'
    grouping chooses on unseen objects and lands at the mean predictor."""
    from embodied_tactile.eval.krr import resolve_cv_grouping

    rng = np.random.default_rng(0)
    n_obj, per_obj, t, d = 32, 4, 10, 8
    code = rng.normal(size=(n_obj, d))
    obj_factors = rng.normal(size=(n_obj, 4))
    def split(objs):
        oid = np.repeat(objs, per_obj)
        lat = code[oid][:, None, :] + 0.05 * rng.normal(size=(len(oid), t, d))
        return {"y": lat, "factors": obj_factors[oid], "object_id": oid,
                "action_index": np.tile(np.arange(per_obj), len(objs)),
                "seq_id": np.array([f"o{o}_{i}" for o, i in zip(oid, range(len(oid)))])}
    train, test = split(np.arange(24)), split(np.arange(24, 32))
    scores = {}
    for groups in ("sequence", "auto"):
        res, align = evaluate_latents(train, test, alignment=alignment_options({"groups": groups, "cv": 4, "readout": "final_segment"}),
                                           split="object")
        scores[groups] = (res.summary()["nmse_trajectory_overall"], align.params["alpha"])
    mean_pred = np.broadcast_to(train["factors"].mean(0), (len(test["factors"]), t, 4))
    mean_nmse = overall(nmse_trajectory(test["factors"], mean_pred))  # the train-mean predictor
    assert scores["sequence"][1] <= 1e-2 and scores["sequence"][0] > mean_nmse + 0.03
    assert scores["auto"][1] >= 10.0 and abs(scores["auto"][0] - mean_nmse) < 0.02
    assert resolve_cv_grouping("auto", "trial") == "sequence" and resolve_cv_grouping("auto", "object") == "object"
    with pytest.raises(ValueError, match=r"alignment.groups='objects' \(str\): expected one of auto, sequence, object"):
        alignment_options({"groups": "objects"})


def test_final_segment_rows():
    lat = np.arange(2 * 10 * 1, dtype=float).reshape(2, 10, 1)
    rows, seq = final_segment_rows(lat, final_segment=0.3, reduce="frames", frames_per_sequence=2)
    assert rows[:, 0].tolist() == [7.0, 9.0, 17.0, 19.0] and seq.tolist() == [0, 0, 1, 1]
    rows, seq = final_segment_rows(lat, final_segment=2, reduce="mean")
    assert rows[:, 0].tolist() == [8.5, 18.5]


def test_nystroem_path_for_large_n():
    tr, te = synthetic_split(600, t=12, seed=7), synthetic_split(100, t=12, seed=8, offset=10_000)
    align = fit_alignment(tr["y"], tr["factors"], readout="final_segment", final_segment=0.25, frames_per_sequence=2, nystroem_threshold=500,
                          n_components=200,
                          cv=3, alphas=(1e-3, 1e-2), gammas=(0.3, 1.0))
    assert align.params["method"] == "nystroem_ridge" and align.params["n_train_rows"] == 1200
    assert np.all(nmse(te["factors"], align.predict(te["y"])[:, -1]) < 0.1)


def test_latent_both_concatenates():
    tr, te = synthetic_split(40, seed=9), synthetic_split(20, seed=10, offset=1000)
    res, align = evaluate_latents(tr, te, latent="both", alignment=alignment_options({"cv": 2, "readout": "final_segment"}))
    assert align.x_mean.shape == (32,) and res.latents_last.shape == (20, 32)


# ------------------------------------------------------------------ baselines
def _obs_split(n, t=16, seed=0, offset=0):
    rng = np.random.default_rng(seed)
    obj = rng.integers(0, 32, n)
    f = np.array([OBJECTS[o].factors() for o in obj])
    tt = np.arange(t) / 30.0
    act = np.zeros((n, t, 6))
    act[:, :, 2] = -(1 - np.cos(2 * np.pi * 0.8 * tt))[None]
    force = (-act[:, :, 2])[:, :, None, None] * (f[:, 2] - 4.0)[:, None, None, None]
    top = force + 0.05 * rng.normal(size=(n, t, 28, 28))
    bot = 0.7 * force + 0.05 * rng.normal(size=(n, t, 28, 28))
    acc = rng.uniform(0, 1, (n, t, 28, 28))
    return {"obs": np.stack([acc, top, bot], 2).astype(np.float32), "actions": act.astype(np.float32), "factors": f,
            "object_id": obj, "action_index": rng.integers(0, 16, n), "seq_id": np.arange(n) + offset}


def test_mean_predictor_nmse_about_one():
    from embodied_tactile.eval.baselines import evaluate_mean

    tr, te = synthetic_split(400, seed=11), synthetic_split(400, seed=12, offset=10_000)
    res = evaluate_mean(tr, te, n_frames=5)
    v = res.subset_nmse()
    assert res.pred.shape == (400, 5, 4)
    assert np.all(np.abs(v - 1.0) < 0.1), v


def test_handcrafted_features_and_krr_baseline():
    from embodied_tactile.eval.baselines import evaluate_handcrafted, handcrafted_features

    tr, te = _obs_split(60, seed=1), _obs_split(20, seed=2, offset=1000)
    feats, names = handcrafted_features(tr["obs"], tr["actions"], ("acc", "fsr_t", "fsr_b"))
    assert feats.shape == (60, 16, len(names)) and np.isfinite(feats).all()
    for k in ("peak_force", "slope_force_depth", "hysteresis", "relaxation", "shear_centroid_offset",
              "top_bottom_diff_energy", "acc_low_band", "acc_high_band", "acc_spectral_centroid"):
        assert k in names
    only_acc, names_acc = handcrafted_features(tr["obs"][:, :, :1], tr["actions"], ("acc",))
    assert all(n.startswith("acc_") for n in names_acc)
    res = evaluate_handcrafted(tr, te, ("acc", "fsr_t", "fsr_b"), alignment=alignment_options({"cv": 3}), modality="multi_l")
    assert res.pred.shape == (20, 16, 4) and np.isfinite(res.pred).all()
    assert res.curve()[-1][2] < 0.3  # stiffness is encoded in the force amplitude (whole-sequence features)


def test_gru_baseline_tiny_run():
    import torch

    torch.set_num_threads(1)
    from embodied_tactile.eval.baselines import GRURegressor, evaluate_gru

    tr, te = _obs_split(12, t=8, seed=3), _obs_split(6, t=8, seed=4, offset=1000)
    res = evaluate_gru(tr, te, gru={"epochs": 2, "hidden": 8, "feat": 8, "batch_size": 4, **WHOLE})
    assert res.pred.shape == (6, 8, 4) and np.isfinite(res.pred).all()
    assert len(res.params["loss_history"]) == 2
    # loader API (iterable of batch dicts) with a batch cap
    batches = [{"obs": torch.as_tensor(tr["obs"][i:i + 4]), "actions": torch.as_tensor(tr["actions"][i:i + 4]),
                "factors": torch.as_tensor(tr["factors"][i:i + 4])} for i in range(0, 12, 4)]
    m = GRURegressor(in_channels=3, hidden=8, feat=8, epochs=1, max_batches_per_epoch=2, **WHOLE).fit(batches)
    assert m.predict(batches).shape == (12, 8, 4)
    # training windows: 3 crops of 5 frames per sequence and epoch -> 3x the optimiser steps
    # of whole sequences; prediction still covers every frame
    seen = []
    w = GRURegressor(in_channels=3, hidden=8, feat=8, epochs=1, batch_size=4, window=5, windows_per_trial=3)
    orig = w.net.forward
    w.net.forward = lambda obs, act: (seen.append(tuple(obs.shape)), orig(obs, act))[1]
    w.fit(tr["obs"], tr["actions"], tr["factors"])
    assert seen == [(4, 5, 3, 28, 28)] * 9
    assert w.predict(te["obs"], te["actions"]).shape == (6, 8, 4)
    with pytest.raises(ValueError, match="need array input"):
        GRURegressor(in_channels=3, window=5).fit(batches)



def _level_split(n: int, seed: int, *, offset: float, step: float, frames: int):
    """n sequences whose single-channel frames carry factor 0 as a per-trial level
    offset + step * (f0 - 1) under N(0, 0.02^2) pixel noise -> (obs, actions (6-d), factors)."""
    rng = np.random.default_rng(seed)
    f = rng.integers(0, 3, size=(n, 4)).astype(float)
    obs = offset + step * (f[:, 0] - 1)[:, None, None, None, None] + 0.02 * rng.standard_normal((n, frames, 1, 28, 28))
    return obs.astype(np.float32), rng.standard_normal((n, frames, 6)).astype(np.float32), f


@pytest.mark.slow
def test_standardised_gru_reads_a_small_level_on_a_large_offset():
    """The acc image at pressing: a per-trial level of +-0.01 on an offset of 0.5 under
    frame noise of 0.02. With input_standardize the GRU reads it; on the raw scale the same
    budget leaves it at the mean predictor (docs/experiments/modality_bounds.md, "Where the pressing
    information is lost")."""
    import torch

    torch.set_num_threads(1)
    from embodied_tactile.eval.baselines import GRURegressor

    (otr, atr, ftr), (ote, ate, fte) = (_level_split(n, seed, offset=0.5, step=0.01, frames=8)
                                        for n, seed in ((48, 0), (24, 1)))
    nmse = {}
    for std in (False, True):
        m = GRURegressor(in_channels=1, hidden=8, feat=8, epochs=15, batch_size=8, lr=3e-3, window=None,
                         windows_per_trial=1, input_standardize=std)
        p = m.fit(otr, atr, ftr).predict(ote, ate)
        nmse[std] = ((p[:, -1, 0] - fte[:, 0]) ** 2).mean() / fte[:, 0].var()
    assert nmse[True] < 0.2 and nmse[False] > 0.5, nmse
    np.testing.assert_allclose(m.in_mean_, [otr.astype(np.float64).mean()], rtol=1e-6)
    np.testing.assert_allclose(m.in_scale_, [otr.astype(np.float64).std()], rtol=1e-5)


@pytest.mark.slow
def test_supervised_latent_filter_arch_reads_a_level_through_its_y_pathway():
    """arch="latent_filter": the Latent Filter's inference path + a linear head on y, trained
    supervised, learns a per-trial level that only its y (through z and the LSTM) can carry;
    Results carry the method name latent_filter_supervised; without a modality it refuses."""
    import torch

    torch.set_num_threads(1)
    from embodied_tactile.eval.baselines import GRURegressor, evaluate_gru

    (otr, atr, ftr), (ote, ate, fte) = (_level_split(n, seed, offset=0.3, step=0.2, frames=6)
                                        for n, seed in ((48, 0), (24, 1)))
    lf = dict(arch="latent_filter", modality="fsr_t", epochs=12, batch_size=8, lr=3e-3, **WHOLE,
              latent_filter={"n_z": 4, "n_y": 4, "encoder": {"widths": [4, 8], "hidden": 16},
                             "transition_hidden": 16, "lstm_hidden": 16})
    m = GRURegressor(in_channels=1, **lf)
    p = m.fit(otr, atr, ftr).predict(ote, ate)
    assert p.shape == (24, 6, 4)
    nmse = ((p[:, -1, 0] - fte[:, 0]) ** 2).mean() / fte[:, 0].var()
    assert nmse < 0.2, nmse
    ids = np.arange(24)
    res = evaluate_gru({"obs": otr, "actions": atr, "factors": ftr, "seq_id": np.arange(100, 148)},
                       {"obs": ote, "actions": ate, "factors": fte, "object_id": ids, "action_index": ids % 4,
                        "seq_id": ids}, gru=dict(lf, epochs=1), modality="fsr_t", skin="soft", primitive="pressing")
    assert res.method == "latent_filter_supervised"
    with pytest.raises(ValueError, match="arch='latent_filter' needs the modality"):
        GRURegressor(in_channels=1, arch="latent_filter")
    with pytest.raises(ValueError, match="arch must be one of"):
        GRURegressor(in_channels=1, arch="lstm")



@pytest.mark.slow
def test_code_regression_recognises_objects_by_a_random_code_and_refuses_other_archs():
    """evaluate_code_regression: the Latent Filter's inference path learns each training
    object's fixed random code from a per-object level, and the KRR maps the predicted codes
    of held-out trials of the same objects to the factor; method latent_filter_codes."""
    import torch

    torch.set_num_threads(1)
    from embodied_tactile.constants import FACTOR_NAMES
    from embodied_tactile.eval.baselines import evaluate_code_regression

    def split(n, seed, offset_id):
        obs, act, f = _level_split(n, seed, offset=0.3, step=0.2, frames=6)
        ids = np.arange(offset_id, offset_id + n)
        return {"obs": obs, "actions": act, "factors": f, "object_id": f[:, 0].astype(int),
                "action_index": ids % 4, "seq_id": ids}

    tr, te = split(48, 0, 0), split(24, 1, 1000)
    lf = dict(arch="latent_filter", modality="fsr_t", epochs=12, batch_size=8, lr=3e-3, **WHOLE, seed=0,
              latent_filter={"n_z": 4, "n_y": 4, "encoder": {"widths": [4, 8], "hidden": 16},
                             "transition_hidden": 16, "lstm_hidden": 16})
    res = evaluate_code_regression(tr, te, gru=lf, alignment=alignment_options({"cv": 2, "alphas": (1e-2,), "gammas": (0.3, 1.0)}),
                                   modality="fsr_t", skin="soft", primitive="pressing")
    assert res.method == "latent_filter_codes"
    assert res.params["gru"]["n_out"] == 4
    assert res.summary()["nmse_last_step"][FACTOR_NAMES[0]] < 0.2
    with pytest.raises(ValueError, match="must be 'latent_filter'"):
        evaluate_code_regression(tr, te, gru=dict(lf, arch="gru"))


# ------------------------------------------------------------------ tables / figures / report
def _results_set():
    out = []
    for prim in ("pressing", "sliding"):
        for skin in ("soft", "hard"):
            tr = synthetic_split(80, t=20, seed=_stable_seed(prim, skin))
            te = synthetic_split(40, t=20, seed=_stable_seed(prim, skin, 1), offset=10_000)
            res, _ = evaluate_latents(tr, te, modality="multi_l", skin=skin, primitive=prim, source="simulated",
                                      alignment=alignment_options({"cv": 2, "alphas": (1e-2,), "gammas": (0.3, 1.0)}),
                                      params={"train_time_s": 12.0})
            out.append(res)
    return out


def test_table_writers(tmp_path):
    from embodied_tactile.eval.tables import table_actions, table_groups, table_runtime, table_summary

    rs = _results_set()
    for t in (table_actions(rs), table_groups(rs), table_summary(rs), table_runtime(rs)):
        md, csv_, tex, js = t.to_markdown(), t.to_csv(), t.to_latex(), t.to_json()
        for text in (md, csv_):
            assert NMSE_DEFINITION in text and "80 train / 40 held-out" in text and "simulated" in text
        assert "\\toprule" in tex and "\\bottomrule" in tex and "Data source: simulated" in tex
        json.dumps(js)
    g = table_groups(rs)  # one block (4 factors + Overall) per modality x skin: multi_l/soft, multi_l/hard
    assert g.columns[:3] == ["Modality", "Skin", "Factor"]
    assert len(g.rows) == 2 * 5 and g.rows[4][2] == "Overall"
    vals = np.array([r[3:] for r in g.rows], dtype=float)
    assert np.isfinite(vals).mean() > 0.9  # cells with sequences are finite
    np.testing.assert_allclose(vals[4], np.nanmean(vals[:4], axis=0))
    a = table_actions(rs)  # 16 action rows per modality x skin block
    assert len(a.rows) == 2 * 16 and a.rows[0][3:5] == [2.0, 0.2]  # pressing A_z, omega_z of action 1


def test_pooled_nmse_equals_nmse_for_one_run():
    from embodied_tactile.eval.tables import pooled_nmse

    rs = _results_set()
    r = rs[0]
    np.testing.assert_allclose(pooled_nmse([r]), nmse_trajectory(r.factors, r.pred))
    m = r.action_index < 8
    np.testing.assert_allclose(pooled_nmse([r], lambda x: x.action_index < 8), r.subset_nmse(m))


@pytest.mark.slow  # the suite's one real UMAP: numba compiles it once per process (import 27 s on a cold cache, fit 18 s)
def test_report_writes_everything(tmp_path):
    """Every table and figure, UMAP included (evaluate.py's own test runs with umap=false), with
    the seeded UMAP's known warning silenced by the filter that matches its real message."""
    from embodied_tactile.eval.figures import class_distances, umap_embed
    from embodied_tactile.eval.report import write_report
    from embodied_tactile.run.quiet import silence_third_party

    rs = _results_set()[:2]
    hist = {"run": [{"train_wall_time_s": 1.0, "nmse_overall": 0.5}, {"train_wall_time_s": 2.0, "nmse_overall": 0.2}]}
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        silence_third_party()
        written = write_report(rs, tmp_path, source="simulated", histories=hist)
    assert not [w for w in seen if "n_jobs" in str(w.message)], [str(w.message) for w in seen]
    with warnings.catch_warnings(record=True) as unfiltered:  # the same fit warns without the filters
        warnings.simplefilter("always")
        tiny = umap_embed(rs[0].latents_last[:9])  # 9 latents: n_neighbors lowered to 8
    assert [w for w in unfiltered if "n_jobs" in str(w.message)], [str(w.message) for w in unfiltered]
    assert tiny.shape == (9, 3) and np.isfinite(tiny).all()
    pngs = [Path(p) for p in written["figures"]]
    assert any("distances" in p.name for p in pngs)
    umaps = sorted(p.name.removeprefix("umap_") for p in pngs if p.name.startswith("umap_"))
    assert umaps and umaps == sorted(p.name.removeprefix("distances_") for p in pngs if p.name.startswith("distances_"))
    assert any("error_vs_runtime" in p.name for p in pngs) and any("nmse_time_by" in p.name for p in pngs)
    for p in pngs:
        assert p.read_bytes()[:4] == b"\x89PNG"
    for ext in ("md", "csv", "tex"):
        assert (tmp_path / f"table_environmentshape.{ext}").exists()
    blob = json.loads((tmp_path / "results.json").read_text())
    assert blob["nmse_definition"] == NMSE_DEFINITION
    assert all(np.isfinite(v) for v in blob["runs"][0]["nmse_trajectory"].values())
    # class distances: cdist between classes, not stacked classes
    x = np.array([[0.0], [0.0], [10.0], [12.0]])
    cls, d = class_distances(x, [0, 0, 1, 1])
    np.testing.assert_allclose(d, [[0.0, 11.0], [11.0, 2.0]])
    cls, d = class_distances(x, [0, 0, 1, 1], mode="centroid")
    np.testing.assert_allclose(d, [[0.0, 11.0], [11.0, 0.0]])


def test_umap_falls_back_to_pca_below_five_latents():
    from embodied_tactile.eval.figures import umap_embed

    x = np.random.default_rng(0).normal(size=(4, 16))
    e = umap_embed(x)
    assert e.shape == (4, 3)
    np.testing.assert_allclose(e.T @ e, np.diag(np.diag(e.T @ e)), atol=1e-9)  # principal axes: uncorrelated
    np.testing.assert_allclose(np.linalg.norm(e, axis=1), np.linalg.norm(x - x.mean(0), axis=1))  # 4 points: 3 axes hold all


def test_results_validation():
    with pytest.raises(ValueError):
        Results(pred=np.zeros((3, 2, 4)), factors=np.zeros((2, 4)), object_id=[0, 1, 2], action_index=[0, 0, 0])


# ------------------------------------------------------------------ configurations, seeds, missing cells
def _fake_run(modality, skin, primitive, seed, err, *, actions=range(16), axes=None, n=48, t=6):
    """A Results whose prediction error has a known scale (no alignment fitted)."""
    rng = np.random.default_rng(_stable_seed(modality, skin, primitive, seed))
    obj = np.arange(n) % 32
    f = np.array([OBJECTS[o].factors() for o in obj])
    sd = np.nanstd(f, axis=0)
    pred = f[:, None, :] + err * sd * rng.normal(size=(n, t, 4))
    acts = np.resize(np.asarray(list(actions)), n)
    return Results(pred=pred, factors=f, object_id=obj, action_index=acts, modality=modality, skin=skin,
                   primitive=primitive, seed=seed, axes=dict(axes or {}), n_train=96,
                   params={"train_time_s": 10.0 + seed})


def test_tables_group_by_every_axis_and_average_over_seeds_only():
    from embodied_tactile.eval.tables import cell_mean, pooled_nmse, table_actions, table_aggregate, table_groups

    rs = ([_fake_run("acc", "soft", "pressing", s, 1.0) for s in range(3)]
          + [_fake_run("multi_l", "soft", "pressing", s, 0.2) for s in range(3)]
          + [_fake_run("multi_l", "hard", "pressing", s, 0.4) for s in range(2)]
          + [_fake_run("multi_l", "soft", "pressing", s, 0.6, axes={"annealing.name": "dvbf"}) for s in range(3)])
    g = table_groups(rs)
    assert g.columns[:4] == ["Modality", "Skin", "annealing.name", "Factor"]
    blocks = {tuple(r[:3]) for r in g.rows}
    assert blocks == {("acc", "soft", "–"), ("multi_l", "soft", "–"), ("multi_l", "hard", "–"),
                      ("multi_l", "soft", "dvbf")}, blocks  # soft never pools acc with multi_l
    for key, runs in {("multi_l", "soft", "–"): rs[3:6], ("multi_l", "hard", "–"): rs[6:8],
                      ("acc", "soft", "–"): rs[:3]}.items():
        row = next(r for r in g.rows if tuple(r[:3]) == key and r[3] == "Overall")
        hard = lambda r: r.group == "hard"  # noqa: E731
        per_seed = [overall(pooled_nmse([r], hard)) for r in runs]  # one value per seed, then the mean
        assert row[4 + 1] == pytest.approx(np.mean(per_seed))  # column hard:pressing
        assert row[4 + 1] == pytest.approx(overall(cell_mean(runs, hard)[0]))
    assert "mean over the seeds" in g.caption and "never averaged together" in g.caption
    a = table_actions(rs)
    assert {tuple(r[:3]) for r in a.rows} == blocks and len(a.rows) == 4 * 16
    agg = table_aggregate(rs)
    col = {c: i for i, c in enumerate(agg.columns)}
    assert len(agg.rows) == 4
    ml = next(r for r in agg.rows if r[1] == "multi_l" and r[2] == "soft" and r[col["annealing.name"]] == "–")
    v = np.array([overall(r.subset_nmse()) for r in rs[3:6]])
    from scipy.stats import t as student_t

    h = student_t.ppf(0.975, 2) * v.std(ddof=1) / np.sqrt(3)
    assert ml[col["n_seeds"]] == 3 and ml[col["seeds"]] == "0,1,2"
    assert ml[col["traj:overall mean"]] == pytest.approx(v.mean()) and ml[col["traj:overall std"]] == pytest.approx(v.std(ddof=1))
    lo, hi = (float(x) for x in ml[col["traj:overall 95% CI"]].strip("[]").split(","))
    assert lo == pytest.approx(v.mean() - h, abs=1e-4) and hi == pytest.approx(v.mean() + h, abs=1e-4)
    hard_row = next(r for r in agg.rows if r[2] == "hard")
    assert hard_row[col["n_seeds"]] == 2 and hard_row[col["traj:overall 95% CI"]] == "–"  # no t interval for n < 3


def test_config_axes_finds_swept_keys_not_derived_ones():
    from embodied_tactile.eval.results import config_axes

    cfgs, names = [], []
    for mod, ch in (("acc", ["acc"]), ("fsr_tb", ["fsr_t", "fsr_b"])):
        for ann in ("linear", "dvbf"):
            for seed in (0, 1):
                name = f"modality={mod},annealing={ann},seed={seed}"
                names.append(name)
                cfgs.append({"seed": seed, "modality": {"name": mod, "channels": ch}, "skin": {"name": "soft"},
                             "primitive": {"name": "pressing"}, "data": {"channels": ch, "seed": seed, "batch_size": 16},
                             "annealing": {"name": ann, "_target_": f"sched.{ann.capitalize()}"},
                             "tags": [mod, ann], "paths": {"log_dir": "logs"},
                             "callbacks": {"ckpt": {"dirpath": f"/x/multi/{name}/checkpoints"}}})
    axes = config_axes(cfgs, names)
    assert axes[0] == {"annealing.name": "linear"} and axes[2] == {"annealing.name": "dvbf"}
    assert config_axes(cfgs[:1], names[:1]) == [{}]
    # a seed-only sweep has no axis: its runs are replicates of one cell
    assert config_axes([c for c in cfgs if c["modality"]["name"] == "acc" and c["annealing"]["name"] == "dvbf"],
                       names[2:4]) == [{}, {}]


def test_tables_never_print_nan():
    from embodied_tactile.eval.report import write_report

    # the default scene uses 4 action sets; sliding only measured two of them
    rs = [_fake_run("multi_l", "soft", "pressing", 0, 0.3, actions=(0, 5, 10, 15)),
          _fake_run("multi_l", "soft", "sliding", 0, 0.3, actions=(0, 5))]
    rs[1].params.pop("train_time_s")  # an unmeasured time
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        written = write_report(rs, tmp, figures=False)
        for p in written["tables"]:
            text = Path(p).read_text()
            assert "nan" not in text.lower(), (p, text)
        md = (Path(tmp) / "table_action_config.md").read_text()
        assert "– = not measured" in md
        assert "– = not measured" in (Path(tmp) / "table_runtime.md").read_text()
        assert "--" in (Path(tmp) / "table_action_config.tex").read_text()
    from embodied_tactile.eval.tables import table_actions

    a = table_actions(rs)
    assert [r[2] for r in a.rows] == [1, 6, 11, 16]  # actions no run used are left out
    c = a.columns.index("sliding:NMSE_1e-2")
    assert np.isfinite(a.rows[0][c]) and np.isnan(a.rows[2][c])  # action 11 was not slid: '–' in print
    assert "| 11 |" in a.to_markdown() and a.to_markdown().count("–") >= 2


# ------------------------------------------------------------------ object codes (eval.codes)
def test_code_diagnostics_against_hand_computations():
    """code_spread: median pairwise Mahalanobis distance; affine_r2: 1 for an affine image,
    about 0 for unrelated codes; own_code_rank: 0 when q(y) sits on its own code, the number
    of nearer codes otherwise; unknown objects and a degenerate input are refused."""
    from embodied_tactile.eval.codes import affine_r2, code_spread, own_code_rank

    codes = np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 4.0]])
    var = np.array([1.0, 4.0])
    # distances: (0,1): 3; (0,2): sqrt(16 / 4) = 2; (1,2): sqrt(9 + 4) = 3.606 -> median 3
    assert code_spread(codes, var) == pytest.approx(3.0)
    rng = np.random.default_rng(0)
    init = rng.normal(size=(32, 4))
    assert affine_r2(init, 0.5 * init @ rng.normal(size=(4, 4)) + 1.0) == pytest.approx(1.0)
    assert affine_r2(init, rng.normal(size=(32, 4))) < 0.4
    y = np.array([[0.1, 0.0], [0.0, 3.9], [2.9, 0.0], [0.0, 0.0]])
    ranks = own_code_rank(y, [0, 2, 1, 1], codes, var)
    # the last sequence (object 1) sits on code 0: code 0 is nearer (0), code 2 (2) nearer than its own (3)
    np.testing.assert_array_equal(ranks, [0, 0, 0, 2])
    # y = (0.1, 0) of object 1 among codes 2 and 1: d(code 2) = 0.01 + 16 / 4 = 4.01 < d(code 1) = 2.9^2 = 8.41
    np.testing.assert_array_equal(own_code_rank(y[:1], [1], codes, var, objects=[2, 1]), [1])
    with pytest.raises(ValueError, match=r"object ids \[0\] have no code"):
        own_code_rank(y[:1], [0], codes, var, objects=[1, 2])
    with pytest.raises(ValueError, match="all equal"):
        affine_r2(init, np.ones_like(init))
    with pytest.raises(ValueError, match="variances must be > 0"):
        code_spread(codes, [1.0, 0.0])


def test_a_relative_data_folder_means_the_training_cwds_even_when_one_of_that_name_is_here(tmp_path, monkeypatch):
    """A run trained elsewhere with paths.data_dir=data reads <training cwd>/data, never a
    ``data`` folder of the evaluating cwd (another data set); a path absent there stays as given."""
    from embodied_tactile.eval.runs import _resolve_path

    train_cwd, here = tmp_path / "train", tmp_path / "here"
    (train_cwd / "data").mkdir(parents=True)
    (here / "data").mkdir(parents=True)
    monkeypatch.chdir(here)
    assert _resolve_path("data", train_cwd) == str(train_cwd / "data")
    assert _resolve_path("elsewhere", train_cwd) == "elsewhere"
    assert _resolve_path(str(here / "data"), train_cwd) == str(here / "data")
    (train_cwd / "raw_1.h5").touch()
    assert _resolve_path("raw_*.h5", train_cwd) == str(train_cwd / "raw_*.h5")


def test_evaluation_options_and_run_selection_without_a_trained_run(tmp_path):
    """eval.pipeline's options (configs/evaluate.yaml + key=value), the split of evaluate.py's
    arguments into options and run selectors, the selection and the output folder, on
    configs alone (test_evaluate.py checks them on trained runs and is slow)."""
    from omegaconf import OmegaConf

    from embodied_tactile.eval import pipeline as ev
    from embodied_tactile.eval.runs import Run

    opts = ev.parse_options(["checkpoint=last", "alignment.cv=2", "baselines=[mean]"])
    assert opts.checkpoint == "last" and opts.alignment.cv == 2 and list(opts.baselines) == ["mean"]
    for bad, match in [(["checkpoint=middle"], "checkpoint='middle' .*one of best, last"),
                       (["latent=w"], "latent='w' .*one of y, z, both"), (["held_out=train"], "held_out='train' .*one of test, val"),
                       (["targets=si"], "targets='si' .*one of design_rank, physical or null"), (["no_such_key=1"], "unknown evaluation option"),
                       (["cv"], "options must be key=value"), (["baselines=[knn]"], r"baselines=\['knn'\] .*a list of untrained, handcrafted")]:
        with pytest.raises(ev.EvaluationError, match=match):
            ev.parse_options(bad)
    options, selection = ev.split_overrides(["alignment.cv=2", "modality=[acc,fsr_t]", "seed=0", "annealing.name=dvbf"])
    assert options == ["alignment.cv=2"]
    assert selection == {"modality": ["acc", "fsr_t"], "seed": ["0"], "annealing.name": ["dvbf"]}

    def run(name, modality, seed):
        cfg = OmegaConf.create({"modality": {"name": modality}, "skin": {"name": "soft"},
                                "primitive": {"name": "pressing"}, "seed": seed})
        return Run(run_dir=tmp_path / name, ckpt=tmp_path / name / "checkpoints" / "best.ckpt", cfg=cfg, name=name)

    runs = [run("a", "acc", 0), run("b", "fsr_t", 1), run("c", "multi_l", 0)]
    assert [r.name for r in ev.select_runs(runs, {"modality": ["acc", "fsr_t"], "seed": ["0.0"]})] == ["a"]
    assert ev.select_runs(runs, {}) == runs
    with pytest.raises(ev.EvaluationError, match="no run matches skin=hard"):
        ev.select_runs(runs, {"skin": ["hard"]})
    with pytest.raises(ev.EvaluationError, match="unknown evaluation option or run selector 'nope'"):
        ev.select_runs(runs, {"nope": ["1"]})
    assert ev.cell(runs[2]) == ("multi_l", "soft", "pressing")
    base = ev.parse_options([])
    assert ev.output_folder(tmp_path / "a", runs[:1], "run", base, {}) == tmp_path / "a" / "evaluation"
    assert ev.output_folder(tmp_path, runs, "multirun", ev.parse_options(["held_out=val"]), {"modality": ["acc"]}) \
        == tmp_path / "evaluation-val-modality=acc"


def test_hybrid_reader_reads_what_the_features_and_the_latents_each_carry():
    """KRR on [hand-crafted features, y]: y carries factor 0 only, the features factor 2
    (stiffness, in the force amplitude) only; the hybrid reads both, each reader alone one."""
    from embodied_tactile.eval.baselines import evaluate_handcrafted, evaluate_hybrid

    channels = ("acc", "fsr_t", "fsr_b")
    tr, te = _obs_split(80, seed=1), _obs_split(30, seed=2, offset=1000)
    rng = np.random.default_rng(3)
    mu, sd = tr["factors"][:, 0].mean(), tr["factors"][:, 0].std()
    for split in (tr, te):
        n, t = split["obs"].shape[:2]
        y = 0.05 * rng.normal(size=(n, t, 4))
        y[:, :, 0] += ((split["factors"][:, 0] - mu) / sd)[:, None]
        split["y"] = y.astype(np.float32)
    kw = dict(alignment=alignment_options({"cv": 3, "readout": "final_segment"}), modality="multi_l")
    hybrid = evaluate_hybrid(tr, te, channels, **kw)
    alone, _ = evaluate_latents(tr, te, **kw)
    features = evaluate_handcrafted(tr, te, channels, **kw)
    assert hybrid.method == "hybrid_krr" and hybrid.pred.shape == (30, 16, 4) and np.isfinite(hybrid.pred).all()
    last = {name: r.curve()[-1] for name, r in (("hybrid", hybrid), ("y", alone), ("features", features))}
    assert last["hybrid"][0] < 0.2 and last["hybrid"][2] < 0.3
    assert last["y"][0] < 0.2 and last["y"][2] > 0.6
    assert last["features"][0] > 0.6 and last["features"][2] < 0.3
    assert hybrid.latents_last.shape[1] == features.latents_last.shape[1] + 4
