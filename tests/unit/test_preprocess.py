"""Tests of data.preprocess and data.cache on small synthetic raw trials."""

from __future__ import annotations

import json
import os

import h5py
import numpy as np
import pytest
import scipy.signal

from embodied_tactile import constants as C
from embodied_tactile.data import cache as cache_mod
from embodied_tactile.data import preprocess as P
from embodied_tactile.data.cache import build_cache, cache_info, list_cached, load_cached
from embodied_tactile.data.preprocess import PreprocessConfig, preprocess_trial, preprocess_trials
from embodied_tactile.data import rawformat
from embodied_tactile.data.rawformat import RawTrial, TrialFormatError, make_attrs, write_trial
from helpers import acc_logmel_naive, fingerprint_file, melspectrogram, power_to_db  # tests/helpers.py


T = 300


def make_trial(rep: int = 0, *, seed: int = 0, t0: float = 50.0, vib=None, fsr_level=None, pose_fn=None) -> RawTrial:
    """10 s trial. ``vib``: {(i, j): (freq Hz, amplitude g)} sine vibrations along z on top
    of gravity (default: every sensor, distinct frequencies); FSR a Gaussian blob moving
    along x; pose a slow pressing cosine unless ``pose_fn(t) -> (M, 6)``."""
    rng = np.random.default_rng(seed + rep)
    n, m = C.N_TACTILE, C.N_POSE
    t = t0 + np.arange(n) / C.FS_TACTILE
    if vib is None:
        vib = {(i, j): (10.0 + 15 * (4 * i + j), 0.05 + 0.01 * j) for i in range(4) for j in range(4)}
    acc = np.zeros((n, 4, 4, 3))
    acc[..., 2] = 1.0
    for (i, j), (f, a) in vib.items():
        acc[:, i, j, 2] += a * np.sin(2 * np.pi * f * (t - t0))
    acc += rng.normal(0, 1e-3, acc.shape)
    yy, xx = np.mgrid[0:16, 0:16]
    if fsr_level is None:
        cx = 8 + 3 * np.sin(2 * np.pi * 0.3 * (t - t0))
        blob = np.exp(-((xx[None] - cx[:, None, None]) ** 2 + (yy[None] - 7) ** 2) / 6.0)
        fsr = np.stack([3000 * blob, 1200 * blob], axis=1) + rng.integers(0, 10, (n, 2, 16, 16))
    else:
        fsr = np.full((n, 2, 16, 16), fsr_level)
    pose_t = t0 + np.arange(m) / C.FS_POSE
    if pose_fn is None:
        pose = np.zeros((m, 6))
        pose[:, 2] = 0.1 + 0.004 * np.cos(2 * np.pi * 0.4 * (pose_t - t0) + np.pi)
    else:
        pose = pose_fn(pose_t - t0)
    attrs = make_attrs(object_id=rep % 32, skin="soft", primitive="pressing", action_index=rep % 16,
                       repetition=rep, source="simulated", seed=seed + rep)
    return RawTrial(t=t, acc=acc.astype(np.float32), fsr=np.clip(fsr, 0, 4095).astype(np.uint16),
                    pose_t=pose_t, pose=pose.astype(np.float32), attrs=attrs)


@pytest.fixture(scope="module")
def cfg() -> PreprocessConfig:
    return PreprocessConfig().validate()


@pytest.fixture(scope="module")
def trial() -> RawTrial:
    return make_trial(0)


@pytest.fixture(scope="module")
def processed(trial, cfg):
    return preprocess_trial(trial, cfg)


# ============================================================================ preprocess
def test_shapes_and_dtypes(processed):
    assert processed["acc"].shape == (T, 28, 28) and processed["acc"].dtype == np.float32
    assert processed["fsr"].shape == (T, 2, 28, 28) and processed["fsr"].dtype == np.float32
    assert processed["actions"].shape == (T, 6) and processed["actions"].dtype == np.float32
    for v in processed.values():
        assert np.isfinite(v).all()
    assert 0.0 <= processed["acc"].min() and processed["acc"].max() <= 1.2
    assert 0.0 <= processed["fsr"].min() and processed["fsr"].max() <= 1.0


def test_fields_computed_only_from_their_inputs(trial, cfg):
    empty = np.zeros((0,))
    acc_only = RawTrial(t=trial.t, acc=trial.acc, fsr=empty, pose_t=empty, pose=empty, attrs=trial.attrs)
    out = preprocess_trial(acc_only, cfg, fields=("acc",))
    assert set(out) == {"acc"}
    pose_only = RawTrial(t=empty, acc=empty, fsr=empty, pose_t=trial.pose_t, pose=trial.pose, attrs=trial.attrs)
    assert set(preprocess_trial(pose_only, cfg, fields=("actions",))) == {"actions"}
    with pytest.raises(ValueError, match="unknown fields"):
        preprocess_trial(trial, cfg, fields=("gyro",))


def test_batched_equals_single(trial, cfg, processed):
    other = make_trial(1)
    batch = preprocess_trials([other, trial], cfg)
    for k, v in processed.items():
        np.testing.assert_allclose(batch[k][1], v, atol=1e-6)


def _direct_librosa(acc_ij: np.ndarray, combine: str = "axes") -> np.ndarray:
    """One sensor by hand with the default parameters: (T, 49) scaled log-mel of |a|
    (``magnitude``) or of the three axes' mel powers summed (``axes``)."""
    a = acc_ij.astype(np.float64)
    sigs = [np.sqrt((a**2).sum(axis=-1))] if combine == "magnitude" else [a[:, k] for k in range(3)]
    s = 0.0
    for sig in sigs:
        sig = (sig - sig.mean()) / 2.0  # static part removed, / 2 g
        y = scipy.signal.resample_poly(sig, 6, 7)
        assert y.shape == (6000,)
        yp = np.pad(y, (54, 54))  # 54 = 128/2 - 20/2: frame k is centred on sample 20k + 10
        s = s + melspectrogram(yp, sr=600, n_fft=128, hop_length=20, win_length=128, window="hann", n_mels=49,
                               fmin=0.0, fmax=300.0)
    assert s.shape == (49, T)
    db = power_to_db(s, amin=1e-10)
    return ((db + 100.0) / 120.0).T


@pytest.mark.slow
@pytest.mark.parametrize("combine", ["axes", "magnitude"])
def test_acc_channel_equals_direct_librosa(trial, combine):
    out = preprocess_trial(trial, PreprocessConfig(acc_combine=combine), fields=("acc",))["acc"]
    i, j = 1, 2
    tile = out[:, 7 * i : 7 * i + 7, 7 * j : 7 * j + 7].reshape(T, 49)
    np.testing.assert_allclose(tile, _direct_librosa(trial.acc[:, i, j], combine), atol=1e-5, rtol=0)


def _lateral_trial(amp_g: float, seed: int = 0) -> RawTrial:
    """make_trial's sensor grid at rest under gravity (z), plus a 90 Hz vibration of
    ``amp_g`` along x on every sensor and 3 mg noise (the simulator's ACC_NOISE_G)."""
    tr = make_trial(seed)
    rng = np.random.default_rng(seed)
    t = tr.t - tr.t[0]
    acc = np.zeros((len(t), 4, 4, 3))
    acc[..., 2] = 1.0
    acc[..., 0] += amp_g * np.sin(2 * np.pi * 90.0 * t)[:, None, None]
    acc += rng.normal(0, 3e-3, acc.shape)
    return RawTrial(t=tr.t, acc=acc.astype(np.float32), fsr=tr.fsr, pose_t=tr.pose_t, pose=tr.pose, attrs=tr.attrs)


def test_lateral_vibration_reaches_the_acc_image():
    """Vibration across gravity (the stick-slip and shear of sliding, mostly in the skin
    plane) must reach the image: a 30 mg lateral tone raises its mel bins by many dB over
    the noise-only trial. |a| (acc_combine=magnitude) keeps it only as (a_x^2 / 2) / 1 g,
    0.45 mg at twice the frequency, under the 3 mg noise: that path cannot tell them apart."""
    quiet, loud = _lateral_trial(0.0), _lateral_trial(0.03, seed=1)

    def gain(cfg):  # largest rise of a time-averaged pixel, scaled dB (0.05 = 6 dB)
        q = preprocess_trial(quiet, cfg, fields=("acc",))["acc"].mean(0)
        return float((preprocess_trial(loud, cfg, fields=("acc",))["acc"].mean(0) - q).max())

    default = gain(PreprocessConfig())
    assert default > 0.1, f"default acc path: a 30 mg lateral tone raised the image by only {default:.3f}"
    mag = gain(PreprocessConfig(acc_combine="magnitude"))
    assert mag < 0.02, f"magnitude path: expected the lateral tone under the noise, got a rise of {mag:.3f}"


@pytest.mark.slow
def test_vectorised_equals_naive_loop(trial, cfg, processed):
    np.testing.assert_allclose(processed["acc"], acc_logmel_naive(trial.acc, cfg), atol=1e-5, rtol=0)


def test_tile_layout_places_sensor_bins():
    mel = np.zeros((3, 49, 4, 4))
    for i in range(4):
        for j in range(4):
            mel[:, :, i, j] = 1000 * i + 100 * j + np.arange(49)
    img = P.tile_layout(mel, (7, 7))
    assert img.shape == (3, 28, 28)
    for i in range(4):
        for j in range(4):
            expect = (1000 * i + 100 * j + np.arange(49)).reshape(7, 7)
            np.testing.assert_array_equal(img[1, 7 * i : 7 * i + 7, 7 * j : 7 * j + 7], expect)


def test_single_vibrating_sensor_lights_its_tile(cfg):
    tr = make_trial(0, vib={(2, 3): (120.0, 0.3)})
    acc = preprocess_trial(tr, cfg, fields=("acc",))["acc"].mean(axis=0)
    tiles = acc.reshape(4, 7, 4, 7).max(axis=(1, 3))
    assert np.unravel_index(np.argmax(tiles), tiles.shape) == (2, 3)
    # a bigger vibration gives a bigger value: the fixed scale keeps amplitude information
    louder = preprocess_trial(make_trial(0, vib={(2, 3): (120.0, 0.6)}), cfg, fields=("acc",))["acc"].mean(axis=0)
    assert louder[14:21, 21:28].max() > acc[14:21, 21:28].max() + 0.03


@pytest.mark.parametrize("shape_in,shape_out", [((16, 16), (28, 28)), ((7, 5), (13, 11)), ((16, 16), (10, 6))])
def test_bilinear_resize_matches_torch(shape_in, shape_out):
    torch = pytest.importorskip("torch")
    x = np.random.default_rng(0).random((3, 2, *shape_in), dtype=np.float32)
    ref = torch.nn.functional.interpolate(torch.from_numpy(x), size=shape_out, mode="bilinear", align_corners=False)
    np.testing.assert_allclose(P.bilinear_resize(x, shape_out), ref.numpy(), atol=1e-6, rtol=0)


def test_win_length_longer_than_n_fft_raises():
    with pytest.raises(ValueError, match=r"win_length \(800\) > n_fft \(128\)"):
        PreprocessConfig(win_length=800, n_fft=128).validate()
    with pytest.raises(ValueError, match=r"n_mels \(70\)"):
        PreprocessConfig(n_mels=70, tile_shape=(7, 10)).validate()
    with pytest.raises(ValueError, match="too many"):  # 49 mels over 0-100 Hz, FFT bins 4.7 Hz apart
        PreprocessConfig(fmax=100.0).validate()
    with pytest.raises(ValueError, match="tile_shape"):  # 48 bins cannot fill a 7 x 7 tile
        PreprocessConfig(n_mels=48).validate()
    with pytest.raises(ValueError, match="resize_hw"):  # 6 x 8 tiles -> 24 x 32 acc image != 28 x 28 FSR
        PreprocessConfig(n_mels=48, tile_shape=(6, 8)).validate()
    with pytest.raises(ValueError, match="hop_length"):
        PreprocessConfig(hop_length=25).validate()
    PreprocessConfig(n_fft=800, win_length=800).validate()  # the paper's window, as n_fft
    PreprocessConfig(n_fft=256, win_length=128).validate()


def test_actions_follow_pose_ramp(cfg):
    rate = np.array([0.002, -0.001, 0.0005, 0.05, -0.02, 0.4])  # m/s and rad/s

    def ramp(tp):
        p = 0.3 + tp[:, None] * rate[None, :]
        p[:, 5] = np.angle(np.exp(1j * p[:, 5]))  # yaw wraps at +-pi during the trial
        return p

    act = preprocess_trial(make_trial(0, pose_fn=ramp), cfg, fields=("actions",))["actions"]
    tc = (np.arange(T) + 0.5) / 30.0
    expect = tc[:, None] * rate[None, :]
    expect[:, :3] *= 1000.0 / 10.0  # mm / 10
    expect[:, 3:] *= 180.0 / np.pi / 10.0  # deg / 10
    np.testing.assert_allclose(act, expect, atol=1e-4)


def test_fsr_block_mean_scale_and_baseline(cfg):
    tr = make_trial(0, fsr_level=100)
    tr.fsr[len(tr.fsr) // 2 :] = 2148  # step at t0 + 5 s = frame 150 boundary
    out = preprocess_trial(tr, cfg, fields=("fsr",))["fsr"]
    np.testing.assert_allclose(out[:150], 100 / 4095, atol=1e-6)
    np.testing.assert_allclose(out[150:], 2148 / 4095, atol=1e-6)
    tr.baseline_t = tr.t[:700] - 20.0
    tr.baseline_fsr = np.full((700, 2, 16, 16), 100, np.uint16)
    out_b = preprocess_trial(tr, cfg, fields=("fsr",))["fsr"]
    np.testing.assert_allclose(out_b[:150], 0.0, atol=1e-7)
    np.testing.assert_allclose(out_b[150:], 2048 / 4095, atol=1e-6)
    assert preprocess_trial(tr, PreprocessConfig(fsr_subtract_baseline=False), fields=("fsr",))["fsr"][0].min() > 0.02


def test_irregular_clock_with_lost_packets(cfg):
    tr = make_trial(0)
    keep = np.ones(len(tr.t), bool)
    keep[1000:1100] = False  # ~143 ms of lost packets, > one frame
    lossy = RawTrial(t=tr.t[keep], acc=tr.acc[keep], fsr=tr.fsr[keep], pose_t=tr.pose_t, pose=tr.pose, attrs=tr.attrs)
    out = preprocess_trial(lossy, cfg)
    ref = preprocess_trial(tr, cfg)
    assert out["acc"].shape == (T, 28, 28) and np.isfinite(out["acc"]).all()
    np.testing.assert_allclose(out["fsr"][100:], ref["fsr"][100:], atol=0.02)
    np.testing.assert_array_equal(out["actions"], ref["actions"])


# ============================================================================ cache
@pytest.fixture()
def raw_file(tmp_path):
    path = tmp_path / "raw.h5"
    for rep in range(3):
        write_trial(path, make_trial(rep))
    return path


@pytest.fixture()
def counter(monkeypatch):
    calls = []
    real = cache_mod.preprocess_trials

    def counting(trials, cfg, fields):
        calls.append((len(trials), tuple(fields)))
        return real(trials, cfg, fields)

    monkeypatch.setattr(cache_mod, "preprocess_trials", counting)
    return calls


@pytest.mark.slow
def test_cache_build_layout_and_reuse(raw_file, tmp_path, cfg, counter):
    paths = build_cache([raw_file], tmp_path / "cache", cfg, workers=1)
    assert set(paths) == {"acc", "fsr", "actions"}
    assert len({p.name for p in paths.values()}) == 3 and all(p.name.startswith(f + "-") for f, p in paths.items())
    assert len(counter) == 1  # one batched call for the chunk, all three fields
    names = [n for n, _ in list_cached(paths["acc"])]
    assert names == sorted(rawformat.trial_name(make_trial(r).attrs) for r in range(3))
    ref = preprocess_trial(make_trial(1), cfg)
    name1 = make_trial(1).name
    for f in ("acc", "fsr", "actions"):
        np.testing.assert_allclose(load_cached(paths[f], name1, f), ref[f], atol=1e-6)
    attrs = dict(list_cached(paths["fsr"]))[name1]
    assert attrs["object_id"] == 1 and attrs["action_index"] == 1 and attrs["spatial_frequency"] == C.OBJECTS[1].spatial_frequency
    info = cache_info(paths["acc"])
    assert info["complete"] and info["n_trials"] == 3 and info["skipped"] == []
    assert info["config"]["n_fft"] == 128 and info["sources"] == [str(raw_file)] and info["key"] in paths["acc"].name
    mtimes = {f: os.stat(p).st_mtime_ns for f, p in paths.items()}
    again = build_cache([raw_file], tmp_path / "cache", cfg, workers=1)
    assert again == paths and len(counter) == 1  # nothing recomputed
    assert {f: os.stat(p).st_mtime_ns for f, p in again.items()} == mtimes
    assert not [p for p in (tmp_path / "cache").iterdir() if ".tmp-" in p.name]


def test_cache_invalidates_on_config_change(raw_file, tmp_path, cfg, counter):
    first = build_cache([raw_file], tmp_path / "cache", cfg, workers=1)
    other = build_cache([raw_file], tmp_path / "cache", PreprocessConfig(n_fft=256, win_length=256), workers=1)
    assert other["acc"] != first["acc"]  # acc config changed -> new key, recomputed
    assert other["fsr"] == first["fsr"] and other["actions"] == first["actions"]
    assert counter[-1] == (3, ("acc",))  # only the stale field was recomputed
    assert cache_info(other["acc"])["config"]["n_fft"] == 256


def test_cache_invalidates_on_source_change(raw_file, tmp_path, cfg, counter):
    first = build_cache([raw_file], tmp_path / "cache", cfg, workers=1)
    tr = make_trial(2)
    tr.acc[:, 0, 0, 2] += (0.01 * np.sin(2 * np.pi * 50.0 * tr.t)).astype(np.float32)  # (a constant offset is
    write_trial(raw_file, tr, overwrite=True)  # the static part preprocessing removes) acc changed, fsr / pose identical
    second = build_cache([raw_file], tmp_path / "cache", cfg, workers=1)
    assert second["acc"] != first["acc"]
    assert second["fsr"] == first["fsr"] and second["actions"] == first["actions"]
    new = load_cached(second["acc"], tr.name, "acc")
    assert not np.allclose(new, load_cached(first["acc"], tr.name, "acc"))


def test_corrupt_trial_is_skipped_and_named(raw_file, tmp_path, cfg):
    bad = make_trial(1).name
    with h5py.File(raw_file, "a") as f:  # truncate one trial's accelerometer stream
        g = f["trials"][bad]
        acc = g["tactile/acc"][:5000]
        del g["tactile/acc"]
        g.create_dataset("tactile/acc", data=acc)
    paths = build_cache([raw_file], tmp_path / "cache", cfg, fields=("acc", "fsr"), workers=1)
    assert bad not in dict(list_cached(paths["acc"])) and len(list_cached(paths["acc"])) == 2
    skipped = cache_info(paths["acc"])["skipped"]
    assert len(skipped) == 1 and skipped[0]["trial"] == bad and skipped[0]["field"] == "acc"
    assert skipped[0]["file"] == str(raw_file) and "tactile/acc" in skipped[0]["problem"]
    assert bad in dict(list_cached(paths["fsr"])) and cache_info(paths["fsr"])["skipped"] == []
    with pytest.raises(TrialFormatError, match=bad):
        build_cache([raw_file], tmp_path / "strict", cfg, fields=("acc",), workers=1, strict=True)
    assert not (tmp_path / "strict").exists() or not any((tmp_path / "strict").iterdir())


@pytest.mark.slow
def test_acc_only_build_never_reads_fsr(raw_file, tmp_path, cfg, monkeypatch):
    seen = []
    real = rawformat.read_trial

    def spy(path, name, fields=rawformat.ALL_REQUIRED_FIELDS, **kw):
        seen.append(tuple(fields))
        return real(path, name, fields, **kw)

    monkeypatch.setattr(rawformat, "read_trial", spy)
    with h5py.File(raw_file, "a") as f:  # no FSR data at all in the raw file
        for g in f["trials"].values():
            del g["tactile/fsr"]
    paths = build_cache([raw_file], tmp_path / "cache", cfg, fields=("acc",), workers=1)
    assert set(paths) == {"acc"} and len(list_cached(paths["acc"])) == 3
    assert seen and all("fsr" not in flds and "pose" not in flds for flds in seen)
    assert not list((tmp_path / "cache").glob("fsr-*"))
    fsr = build_cache([raw_file], tmp_path / "cache", cfg, fields=("fsr",), workers=1)["fsr"]
    assert len(list_cached(fsr)) == 0 and len(cache_info(fsr)["skipped"]) == 3


@pytest.mark.slow
def test_process_pool_build_equals_in_process(raw_file, tmp_path, cfg):
    """The pool (fingerprints hashed per chunk in the workers, arrays handed back through
    shared slots that are reused across chunks, attrs from the scan) writes the same caches
    as the in-process build: keys, arrays bit for bit, trial attrs with their types, skips."""
    for rep in range(3, 7):
        write_trial(raw_file, make_trial(rep))
    bad = make_trial(4).name
    with h5py.File(raw_file, "a") as f:
        f["trials"][bad]["tactile/fsr"][3, 0, 0, 0] = 5000  # fsr skipped, acc and actions kept
    serial = build_cache([raw_file], tmp_path / "a", cfg, workers=1)
    pooled = build_cache([raw_file], tmp_path / "b", cfg, workers=2, chunk_size=1)  # 7 chunks, 4 slots
    for f in serial:
        assert serial[f].name == pooled[f].name  # same key
        listed = list_cached(serial[f])
        assert len(listed) == (6 if f == "fsr" else 7)
        assert [n for n, _ in listed] == [n for n, _ in list_cached(pooled[f])]
        with h5py.File(serial[f], "r") as a, h5py.File(pooled[f], "r") as b:
            for name, _ in listed:
                ga, gb = a["trials"][name], b["trials"][name]
                assert ga[f][()].tobytes() == gb[f][()].tobytes()
                assert list(ga.attrs) == list(gb.attrs)
                for k in ga.attrs:
                    assert ga.attrs.get_id(k).get_type() == gb.attrs.get_id(k).get_type(), k
                    assert type(ga.attrs[k]) is type(gb.attrs[k]) and np.array_equal(ga.attrs[k], gb.attrs[k]), k
        assert cache_info(serial[f])["skipped"] == cache_info(pooled[f])["skipped"]
    assert [s["trial"] for s in cache_info(pooled["fsr"])["skipped"]] == [bad]
    assert json.loads(h5py.File(pooled["acc"], "r").attrs["sources"]) == [str(raw_file)]
    assert fingerprint_file(raw_file, [n for n, _ in list_cached(serial["acc"])], ("acc",))["acc"] == (
        cache_info(serial["acc"])["source_digests"][0]
    )  # the serial fingerprint and the pool's per-chunk one agree


def test_duplicate_trial_names_across_files_are_an_error(raw_file, tmp_path, cfg):
    """A trial name in two raw files is an error naming both (docs/reference/data_format.md, trial
    identity), never one copy cached and the other skipped; the same file twice is read once."""
    other = tmp_path / "other.h5"
    write_trial(other, make_trial(0))  # same canonical name as raw_file's first trial
    with pytest.raises(TrialFormatError, match="duplicate") as info:
        build_cache([raw_file, other, raw_file], tmp_path / "cache", cfg, fields=("actions",), workers=1)
    assert str(raw_file) in str(info.value) and str(other) in str(info.value) and make_trial(0).name in str(info.value)
    path = build_cache([raw_file, raw_file], tmp_path / "cache", cfg, fields=("actions",), workers=1)["actions"]
    info = cache_info(path)
    assert info["n_trials"] == 3 and info["sources"] == [str(raw_file)] and info["skipped"] == []


@pytest.mark.parametrize("n", [7000, 6993, 7001])
def test_resample_equals_resample_poly(n):
    """The block-product resampler (lengths that are multiples of 7) and its resample_poly
    fallback give scipy's resample_poly to float32 precision, edges included."""
    x = np.random.default_rng(n).normal(0, 0.1, size=(2, 3, n))
    ref = scipy.signal.resample_poly(x, 6, 7, axis=-1)
    out = P.resample(x, 6, 7)
    assert out.dtype == np.float32 and out.shape == ref.shape
    np.testing.assert_allclose(out, ref, atol=2e-7, rtol=0)


def test_cache_key_changes_with_preprocess_version(monkeypatch, cfg):
    from embodied_tactile.data import cache as cache_mod

    key = cache_mod.cache_key("acc", cfg, ["digest"])
    monkeypatch.setattr(cache_mod, "PREPROCESS_VERSION", P.PREPROCESS_VERSION + 1)
    assert cache_mod.cache_key("acc", cfg, ["digest"]) != key


def test_pool_workers_end_on_sigterm_whatever_handler_train_py_installed(monkeypatch):
    """A forked worker inherits train.py's stop handlers (SIGTERM recorded, not fatal); the
    pools' initialisers give SIGTERM its default action back (Pool.terminate ends workers with
    it; a worker that only recorded it left a sweep's data preparation waiting forever) and
    leave Ctrl-C to the parent."""
    import signal

    from embodied_tactile.run import workers
    from embodied_tactile.run.runfolder import StopSignals
    from embodied_tactile.sim import dataset as sim_dataset

    monkeypatch.setattr(workers, "one_blas_thread", lambda: None)  # the worker's thread limit, not this process's
    monkeypatch.setattr(workers, "hold_freed_memory", lambda: None)  # the worker's allocator, not this process's
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, os.environ.get(var, ""))  # restored after the test
    saved = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    assert cache_mod.init_worker is sim_dataset.init_worker is workers.init_worker  # both pools start alike
    try:
        StopSignals().install()
        workers.init_worker()
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        for s, h in saved.items():
            signal.signal(s, h)


def test_a_hole_in_the_scenes_window_skips_the_trial():
    """Fault: a 20 s recording with a 1.5 s hole (lost packets listed) in its first 10 s,
    the scene's window: 7.5 % of the trial, within MAX_MISSING_SHARE, but 15 % of the window
    the resampling would interpolate. Before: used without a word. Now: every field of the
    trial gets the problem, naming the share and the hole; the same hole after the window
    does not count."""
    fs = C.FS_TACTILE
    t = np.arange(int(20 * fs)) / fs
    attrs = {"fs_tactile": fs}
    cfg = PreprocessConfig()

    def trial(t):
        return RawTrial(t=t, acc=None, fsr=None, pose_t=None, pose=None, attrs=attrs)

    inside = t[(t < 3.0) | (t >= 4.5)]
    probs, _ = P.time_problems(trial(inside), cfg, ("acc", "fsr"))
    assert set(probs) == {"acc", "fsr"}
    assert probs["acc"].startswith("tactile/t: 15.0% of the samples of the scene's 10 s window missing")
    assert "largest gap 1.5 s at 3 s" in probs["acc"] and "MAX_MISSING_SHARE" in probs["acc"]
    after = t[(t < 13.0) | (t >= 14.5)]
    assert P.time_problems(trial(after), cfg, ("acc",))[0] == {}
