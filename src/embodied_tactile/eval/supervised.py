"""The supervised references' training (the conv + GRU and the Latent Filter's inference
path told the factors, :class:`~embodied_tactile.eval.baselines.GRURegressor`) as a
LightningModule, run by the same Lightning ``Trainer`` as the Latent Filter: masked mean
squared error of standardised targets at every frame, Adam."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn


class SupervisedRegression(L.LightningModule):
    """``net(obs, actions)`` -> (B, T, n_out) trained on the batch's standardised
    ``target`` (B, n_out; NaN = unknown, left out of the loss) at every frame."""

    def __init__(self, net: nn.Module, lr: float, weight_decay: float = 0.0) -> None:
        super().__init__()
        self.net = net
        self.lr, self.weight_decay = float(lr), float(weight_decay)
        self.epoch_losses: list[float] = []
        self._sum, self._count = 0.0, 0

    def training_step(self, batch: Mapping[str, Tensor], batch_idx: int) -> Tensor:
        y = batch["target"]
        mask = torch.isfinite(y)
        out = self.net(batch["obs"], batch["actions"])
        target = torch.where(mask, y, torch.zeros_like(y))[:, None, :].expand_as(out)
        m = mask[:, None, :].expand_as(out).float()
        loss = (((out - target) ** 2) * m).sum() / m.sum().clamp_min(1.0)
        self._sum += float(loss.detach())
        self._count += 1
        return loss

    def on_train_epoch_end(self) -> None:
        self.epoch_losses.append(self._sum / max(self._count, 1))
        self._sum, self._count = 0.0, 0

    def configure_optimizers(self) -> torch.optim.Optimizer:
        return torch.optim.Adam(self.net.parameters(), lr=self.lr, weight_decay=self.weight_decay)


class EpochBatches:
    """An iterable the Trainer re-iterates every epoch: ``make()`` yields one epoch's batch
    dicts, ``to_batch`` turns each into tensors."""

    def __init__(self, make: Callable[[], Iterable[Mapping[str, Any]]],
                 to_batch: Callable[[Mapping[str, Any]], dict[str, Tensor]]) -> None:
        self.make, self.to_batch = make, to_batch

    def __iter__(self) -> Iterator[dict[str, Tensor]]:
        return (self.to_batch(b) for b in self.make())


def fit(module: SupervisedRegression, batches: EpochBatches, epochs: int, max_batches_per_epoch: int | None,
        device: str = "cpu") -> SupervisedRegression:
    """Train ``module`` for ``epochs`` passes over ``batches`` (at most
    ``max_batches_per_epoch`` each) with a plain Lightning Trainer; returns it in eval mode."""
    trainer = L.Trainer(max_epochs=int(epochs), accelerator=device, devices=1, logger=False,
                        enable_checkpointing=False, enable_progress_bar=False, enable_model_summary=False,
                        limit_train_batches=max_batches_per_epoch if max_batches_per_epoch is not None else 1.0,
                        limit_val_batches=0, num_sanity_val_steps=0)
    trainer.fit(module, train_dataloaders=batches)
    return module.eval()
