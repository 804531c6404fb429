"""Figures a reader can read: structure of each figure (panels, axis labels, log NMSE axes,
legend labels unique / short / readable, facets for sweeps, distance-matrix order, captions)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

from embodied_tactile.constants import HETEROGENEOUS_OBJECTS, SOFT_OBJECTS, get_object  # noqa: E402
from embodied_tactile.eval import figures as F  # noqa: E402


def _legend_labels(fig) -> list[str]:
    out = [t.get_text() for lg in fig.legends for t in lg.get_texts()]
    for ax in fig.axes:
        if ax.get_legend():
            out += [t.get_text() for t in ax.get_legend().get_texts()]
    return out


@pytest.mark.slow
def test_nmse_curves_one_readable_legend_log_axis():
    curves = {k: np.abs(np.random.default_rng(0).normal(size=(30, 4))) + 0.01 for k in ("multi_l", "acc", "fsr_tb")}
    fig = F.nmse_curves_figure(curves, title="Held-out NMSE vs interaction time, by modality")
    try:
        assert len(fig.axes) == 5
        labels = _legend_labels(fig)
        assert sorted(labels) == sorted(["MULTI-L", "ACC", "FSR$_{tb}$"])  # once each, in words
        assert all(ax.get_yscale() == "log" for ax in fig.axes)
        assert fig.axes[0].get_ylabel() == "held-out NMSE (log scale)"
        assert all(ax.get_xlabel() == "interaction time (s)" for ax in fig.axes)
        assert "..." not in fig._suptitle.get_text() and "\n" not in fig._suptitle.get_text()
    finally:
        plt.close(fig)


def _runs(modalities, skins, prims):
    hist, points = {}, {}
    for m in modalities:
        for s in skins:
            for p in prims:
                key = f"{m}/{s}/{p}"
                hist[key] = [{"train_wall_time_s": 10.0 * k, "nmse_overall": 1.0 / k} for k in range(1, 4)]
                for method in ("latent_filter", "handcrafted_krr", "mean"):
                    points[f"{method}/{key}"] = (30.0, 0.5)
    return hist, points


@pytest.mark.slow
def test_error_vs_runtime_facets_per_modality_and_short_unique_legend():
    hist, points = _runs(["acc", "fsr_t", "fsr_b", "fsr_tb", "multi_e", "multi_l"], ["soft", "hard"],
                         ["pressing", "precession", "sliding"])
    fig = F.error_vs_runtime_figure(hist, title="Held-out NMSE vs training time", points=points)
    try:
        visible = [ax for ax in fig.axes if ax.get_visible()]
        assert len(visible) == 6  # one panel per modality, not one legend entry per run
        assert [ax.get_title() for ax in visible] == ["ACC", "FSR$_t$", "FSR$_b$", "FSR$_{tb}$", "MULTI-E", "MULTI-L"]
        labels = _legend_labels(fig)
        assert len(labels) == len(set(labels)) <= 10  # 6 scenes + line + 3 methods (was ~27 run labels)
        assert all(len(lab) <= 45 for lab in labels)
        assert not any(lab.count("/") for lab in labels)  # no "handcrafted_krr/handcrafted_krr/..." keys
        assert {"Latent Filter", "Hand-crafted + KRR", "Mean predictor", "soft, pressing"} <= set(labels)
        assert all(ax.get_yscale() == "log" for ax in visible)
        assert all("log scale" in ax.get_ylabel() for ax in visible if ax.get_ylabel())
        assert any(ax.get_xlabel() == "training time (s)" for ax in visible)
    finally:
        plt.close(fig)



def test_error_vs_runtime_line_is_the_checks_without_the_final_alignment():
    """The line traces the periodic checks; the final alignment (another read-out of the last
    check's weights) is not a point of it."""
    rows = [{"train_wall_time_s": 0.0, "nmse_overall": 1.0, "initial": True},
            {"train_wall_time_s": 10.0, "nmse_overall": 0.5}, {"train_wall_time_s": 20.0, "nmse_overall": 0.4},
            {"train_wall_time_s": 20.5, "nmse_overall": 0.3, "final": True}]
    fig = F.error_vs_runtime_figure({"multi_l/soft/pressing": rows})
    try:
        (line,) = [ln for ax in fig.axes for ln in ax.get_lines() if len(ln.get_xdata()) > 1]
        assert list(line.get_xdata()) == [0.0, 10.0, 20.0] and list(line.get_ydata()) == [1.0, 0.5, 0.4]
    finally:
        plt.close(fig)

def test_umap_one_panel_per_factor_coloured_by_level():
    obj = np.repeat(np.arange(32), 2)
    fac = np.stack([get_object(o).factors() for o in obj])
    emb = np.random.default_rng(0).normal(size=(len(obj), 3))
    fig = F.umap_figure(None, fac, title="UMAP", embedding=emb)
    try:
        assert len(fig.axes) == 4
        assert [ax.get_title() for ax in fig.axes] == ["Spatial Freq. (1/m)", "Amplitude (mm)", "Stiffness (log10 Pa)",
                                                      "Heterogeneity (0/1)"]
        for ax in fig.axes:
            assert (ax.get_xlabel(), ax.get_ylabel(), ax.get_zlabel()) == ("UMAP 1", "UMAP 2", "UMAP 3")
        levels = [[t.get_text() for t in ax.get_legend().get_texts()] for ax in fig.axes]
        assert levels[0] == ["10", "30", "50"] and levels[1] == ["5", "10", "20"] and levels[3] == ["0", "1"]
        assert len(levels[2]) == 3  # the three bulk materials
    finally:
        plt.close(fig)


def test_distance_matrix_ordered_by_group_and_levels_groups_marked():
    classes = np.arange(32)
    order = F.object_order(classes)
    groups = [get_object(int(classes[i])).group for i in order]
    assert groups == ["soft"] * len(SOFT_OBJECTS) + ["hard"] * (27 - len(SOFT_OBJECTS)) + ["heterogeneous"] * len(
        HETEROGENEOUS_OBJECTS)
    soft = [int(classes[i]) for i in order][: len(SOFT_OBJECTS)]
    keys = [tuple(get_object(o).factors()[:3]) for o in soft]
    assert keys == sorted(keys)  # frequency, then amplitude, then stiffness
    dist = np.abs(np.subtract.outer(classes, classes)).astype(float)
    fig = F.distance_figure(classes, dist, title="t")
    try:
        ax = fig.axes[0]
        ticks = [int(t.get_text()) for t in ax.get_xticklabels()]
        assert ticks == [int(classes[i]) for i in order] == [int(t.get_text()) for t in ax.get_yticklabels()]
        img = ax.images[0].get_array()
        np.testing.assert_allclose(img, (dist / dist.max())[np.ix_(order, order)])  # reordered, not relabelled
        assert {t.get_text() for t in ax.texts} == {"soft", "hard", "heterogeneous"}
        assert len(ax.lines) == 4  # two group boundaries, horizontal + vertical
        assert ax.get_xlabel().startswith("object id") and ax.get_ylabel() == "object id"
    finally:
        plt.close(fig)


def test_captions_hold_the_long_definitions(tmp_path):
    note = "NMSE = mean squared error / variance. Splits: 48 train / 16 held-out."
    names = ["nmse_time_by_modality.png", "umap_x.png", "distances_x.png", "error_vs_runtime.png"]
    p = F.write_captions([tmp_path / n for n in names], note, tmp_path / "captions.md")
    text = p.read_text()
    for n in names:
        assert f"**{n}**" in text
    assert text.count(note) == 4 and "logarithmic" in text and "ordered by group" in text


@pytest.mark.parametrize("value, expected", [("multi_l", "MULTI-L"), ("handcrafted_krr", "Hand-crafted + KRR"),
                                             ("acc@seed=1", "ACC (seed=1)"), ("soft", "soft")])
def test_readable(value, expected):
    assert F.readable(value) == expected


@pytest.mark.slow
def test_log_axis_clipped_when_a_few_values_are_near_zero_and_plain_tick_labels():
    c = np.full((30, 4), 0.5)
    c[1, 1] = 1e-11  # one frame of a tiny held-out set: would stretch the axis over ten decades
    fig = F.nmse_curves_figure({"multi_l": c, "acc": c * 2})
    try:
        ax = fig.axes[0]
        assert ax.get_ylabel() == "held-out NMSE (log scale, clipped at 0.01)"
        assert ax.get_ylim()[0] == pytest.approx(0.01)
        fig.canvas.draw()
        labels = [t.get_text() for t in ax.get_yticklabels() if t.get_text()]
        assert labels and all("times" not in lab and "^" not in lab for lab in labels)  # 0.1, 1: not 10^-1
        ys = np.concatenate([line.get_ydata() for line in fig.axes[1].get_lines()])
        assert np.nanmin(ys) == pytest.approx(0.01)  # the near-zero frame drawn at the clip
    finally:
        plt.close(fig)
    fig = F.nmse_curves_figure({"multi_l": np.full((30, 4), 0.5), "acc": np.full((30, 4), 0.05)})
    try:
        assert fig.axes[0].get_ylabel() == "held-out NMSE (log scale)"  # nothing cut: nothing said
    finally:
        plt.close(fig)
    fig = F.nmse_curves_figure({"multi_l": np.full((30, 4), 1.2), "acc": np.full((30, 4), 1.6)})
    try:  # less than a decade: minor ticks labelled, so the axis is readable
        fig.canvas.draw()
        ax = fig.axes[0]
        shown = [t.get_text() for t in ax.get_yticklabels(minor=True) + ax.get_yticklabels() if t.get_text()]
        assert len(shown) >= 2 and all("^" not in s for s in shown)
    finally:
        plt.close(fig)


def test_distance_group_names_sit_on_the_matrix_not_over_the_title():
    classes = np.array([0, 8, 17, 27])
    fig = F.distance_figure(classes, np.ones((4, 4)), title="t")
    try:
        ax = fig.axes[0]
        assert [t.get_position()[1] for t in ax.texts] == [1.01] * len(ax.texts)  # axes fraction, just above
        assert ax.get_title() == "t"
    finally:
        plt.close(fig)


def test_umap_colours_are_physical_levels_and_curves_in_paper_order():
    from embodied_tactile.eval.results import Results
    from embodied_tactile.eval.targets import encode_factors

    ids = np.array([0, 8, 17, 27])
    cat = np.stack([get_object(o).factors() for o in ids])
    ranks = encode_factors(cat, "design_rank")
    fac = F.physical_factors(Results(factors=ranks, object_id=ids, action_index=np.zeros(4, int), pred=ranks))
    np.testing.assert_allclose(fac, cat)
    assert set(fac[:, 0]) <= {10.0, 30.0, 50.0}  # 1/m, not the design ranks 0 / 1 / 2
    # an object outside the catalogue: its trials' own factors, kept by the evaluation
    own = cat + 1.0
    fac = F.physical_factors(Results(factors=ranks, object_id=ids + 40, action_index=np.zeros(4, int), pred=ranks,
                                     factors_physical=own))
    np.testing.assert_allclose(fac, own)

    rs = [Results(method="latent_filter", modality=m, skin="soft", primitive="pressing", factors=fac,
                  object_id=np.array([0, 8, 17, 27]), action_index=np.zeros(4, int), pred=np.repeat(fac[:, None], 3, 1))
          for m in ("multi_l", "fsr_b", "acc", "fsr_t")]
    assert list(F.curves_by(rs, "modality")) == ["acc", "fsr_t", "fsr_b", "multi_l"]


def test_curves_by_modality_shade_the_range_over_seeds():
    """Each seed's runs pooled into its own curve; the figure shades their range around the
    pooled line (the paper's bands), and a label with one seed gets no band."""
    from matplotlib.collections import PolyCollection

    from embodied_tactile.eval import Results

    rng = np.random.default_rng(0)
    y = rng.normal(size=(6, 4))

    def run(modality, seed, noise):
        return Results(method="latent_filter", modality=modality, skin="soft", primitive="pressing", seed=seed,
                       factors=y, object_id=np.arange(6), action_index=np.zeros(6, int), var_ref=np.ones(4),
                       pred=y[:, None] + noise * rng.normal(size=(6, 20, 4)))

    rs = [run("multi_l", 0, 0.1), run("multi_l", 1, 0.5), run("acc", 0, 0.3)]
    bands = F.seed_curves_by(rs, "modality")
    assert list(bands) == ["multi_l"] and bands["multi_l"].shape == (2, 20, 4)
    from embodied_tactile.eval.tables import pooled_nmse

    np.testing.assert_allclose(bands["multi_l"][1], pooled_nmse([rs[1]], curve=True))
    assert (bands["multi_l"][0] < bands["multi_l"][1]).mean() > 0.9  # the noisier seed reads worse
    fig = F.nmse_curves_figure(F.curves_by(rs, "modality"), bands=bands)
    try:
        shaded = [sum(isinstance(c, PolyCollection) for c in ax.collections) for ax in fig.axes[:5]]
        assert shaded == [1] * 5  # multi_l's band in every panel, none for acc
    finally:
        plt.close(fig)
