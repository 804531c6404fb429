"""The training split's channel statistics handed from the data to the model when a fit
starts (:class:`HandOverStatistics`): the model's input standardisation reads them."""

from __future__ import annotations

import lightning as L


class HandOverStatistics(L.Callback):
    """Hands the DataModule's training statistics (``datamodule.statistics``, computed in its
    ``setup("fit")``) to the module (``use_data_statistics``) at the start of fit, after a
    resumed run's checkpoint is restored and before the first step: the data owns its
    statistics, the model never reaches for the DataModule. A module without
    ``use_data_statistics`` or a DataModule without statistics is left as it is."""

    def on_fit_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        statistics = getattr(trainer.datamodule, "statistics", None)
        if statistics is not None and hasattr(pl_module, "use_data_statistics"):
            pl_module.use_data_statistics(statistics)


__all__ = ["HandOverStatistics"]
