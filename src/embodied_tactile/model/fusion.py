"""Observation models of the Latent Filter: where the modality's channels are fused.

Both classes map frames o (N, C, 28, 28) to the measurement Gaussian q(z | o)
(``encode`` -> mean, variance (N, n_z), float32) and latents z (N, n_z) back to
observation means (``decode`` -> (N, C, 28, 28), channels in ``obs`` order).

* :class:`EarlyFusion` (``fusion: single`` or ``early``): the channels are fused before
  the network, by stacking: ONE :class:`~.networks.ConvEncoder` over all C channels and
  one :class:`~.networks.ConvDecoder` producing all of them.
* :class:`LateFusion` (``fusion: late``): one encoder/decoder per pathway (a group of
  channels, e.g. vibration [acc] and force [fsr_t, fsr_b]); the pathways' Gaussians are
  multiplied in latent space (:func:`~.networks.fuse_gaussians`, float32, variance form)
  and the decoders' outputs are concatenated and put back in ``obs`` channel order.

:func:`observation_model` picks the class from the modality's ``fusion``; the Lightning
module (:mod:`.module`) trains whichever the network built.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from .networks import ConvDecoder, ConvEncoder, fuse_gaussians


class EarlyFusion(nn.Module):
    """One encoder over the stacked channels and one decoder for all of them.

    Args: n_channels (C), n_z, widths / hidden (the :class:`ConvEncoder` sizes, shared by
    the decoder), min_var (encoder variance floor)."""

    def __init__(self, n_channels: int, n_z: int, widths: Sequence[int], hidden: int, min_var: float) -> None:
        super().__init__()
        self.encoder = ConvEncoder(n_channels, n_z, widths, hidden, min_var)
        self.decoder = ConvDecoder(n_channels, n_z, widths, hidden)

    def encode(self, o: Tensor) -> tuple[Tensor, Tensor]:
        return self.encoder(o)

    def decode(self, z: Tensor) -> Tensor:
        return self.decoder(z)


class LateFusion(nn.Module):
    """One encoder/decoder per pathway, integrated in latent space by a product of Gaussians.

    Args: pathways ``[(name, [channel indices into obs]), ...]`` (at least two, together a
    partition of the C channels; :meth:`Modality.pathway_indices
    <embodied_tactile.data.modality.Modality.pathway_indices>`), then the sizes as for
    :class:`EarlyFusion`. ``encoders`` / ``decoders`` are keyed by pathway name.
    """

    def __init__(self, pathways: Sequence[tuple[str, Sequence[int]]], n_z: int, widths: Sequence[int],
                 hidden: int, min_var: float) -> None:
        super().__init__()
        pathways = [(str(name), [int(i) for i in idx]) for name, idx in pathways]
        order = [i for _, idx in pathways for i in idx]
        if len(pathways) < 2 or sorted(order) != list(range(len(order))):
            raise ValueError(f"late fusion needs >= 2 pathways partitioning the channels 0..C-1, got {pathways}")
        self.encoders = nn.ModuleDict()
        self.decoders = nn.ModuleDict()
        self.pathways = pathways
        for name, idx in pathways:  # encoder then decoder per pathway: the initialisation order of the RNG draws
            self.encoders[name] = ConvEncoder(len(idx), n_z, widths, hidden, min_var)
            self.decoders[name] = ConvDecoder(len(idx), n_z, widths, hidden)
            self.register_buffer(f"_idx_{name}", torch.tensor(idx, dtype=torch.long), persistent=False)
        self._identity_order = order == list(range(len(order)))
        self.register_buffer("_inv_order", torch.argsort(torch.tensor(order)), persistent=False)

    def _channels(self, o: Tensor, name: str, idx: list[int]) -> Tensor:
        if idx == list(range(idx[0], idx[-1] + 1)):
            return o[:, idx[0]:idx[-1] + 1]  # contiguous channels: a view
        return o.index_select(1, getattr(self, f"_idx_{name}"))

    def encode(self, o: Tensor) -> tuple[Tensor, Tensor]:
        """Each pathway's Gaussian from its channels, multiplied (normalised, float32) in
        pathway order."""
        m = v = None
        for name, idx in self.pathways:
            mi, vi = self.encoders[name](self._channels(o, name, idx))
            m, v = (mi, vi) if m is None else fuse_gaussians(m, v, mi, vi)
        return m, v

    def decode(self, z: Tensor) -> Tensor:
        x = torch.cat([self.decoders[name](z) for name, _ in self.pathways], dim=1)
        return x if self._identity_order else x.index_select(1, self._inv_order)


ObservationModel = EarlyFusion | LateFusion

#: modality ``fusion`` -> the class that implements it
FUSION_CLASSES: dict[str, type[ObservationModel]] = {"single": EarlyFusion, "early": EarlyFusion, "late": LateFusion}


def observation_model(fusion: str, pathways: Sequence[tuple[str, Sequence[int]]], n_z: int,
                      widths: Sequence[int], hidden: int, min_var: float) -> ObservationModel:
    """The observation model of a modality with this ``fusion`` and ``pathways``
    (``[(name, [channel indices]), ...]``; one pathway over all channels unless late)."""
    cls = FUSION_CLASSES.get(fusion)
    if cls is None:
        raise ValueError(f"unknown fusion {fusion!r}; known: {sorted(FUSION_CLASSES)}")
    if cls is LateFusion:
        return LateFusion(pathways, n_z, widths, hidden, min_var)
    (_, idx), = pathways  # one pathway over every channel
    return EarlyFusion(len(idx), n_z, widths, hidden, min_var)
