"""``callbacks.so3_plot``: the validation images' distributions drawn into the run directory.

Quick tier: a tiny matrix Fisher network trained in this process on 20 random images (5 batches of 4
per epoch), its distributions drawn on the level-1 grid.
"""

from __future__ import annotations

import functools

import lightning.pytorch as pl
import pytest
import torch
from torch import nn
from torch.utils.data import DataLoader

from conftest import haar_rotations
from image2sphere.nn import MatrixFisherNet
from image2sphere.training import PoseEstimationModule
from image2sphere.training.callbacks import SO3PlotCallback

IMAGE_SIZE, N_IMAGES, BATCH = 8, 20, 4


class _Encoder(nn.Module):
    out_channels = 2

    def feature_size(self, image_size):
        return (image_size, image_size)

    def forward(self, images):
        return images[:, :2]


class _Data(pl.LightningDataModule):
    def __init__(self):
        super().__init__()
        g = torch.Generator().manual_seed(0)
        images = torch.randn(N_IMAGES, 3, IMAGE_SIZE, IMAGE_SIZE, generator=g)
        rotations = haar_rotations(N_IMAGES, seed=1, dtype=torch.float32)
        self.data_train = [{"image": images[i], "rotation": rotations[i], "index": i} for i in range(N_IMAGES)]
        self.data_val = [
            {"image": images[i], "rotations": rotations[i][None], "mask": torch.ones(1, dtype=torch.bool),
             "index": i, "class_index": torch.tensor(0)}
            for i in range(4)
        ]  # fmt: skip

    def train_dataloader(self):
        return DataLoader(self.data_train, batch_size=BATCH)

    def val_dataloader(self):
        return DataLoader(self.data_val, batch_size=BATCH)


class _CountValidations(pl.Callback):
    def __init__(self):
        self.steps: list[int] = []

    def on_validation_epoch_end(self, trainer, module):
        if not trainer.sanity_checking:
            self.steps.append(trainer.global_step)


@pytest.mark.filterwarnings("ignore::UserWarning")  # Lightning's notes on workers and tiny data sets
@pytest.mark.parametrize("val_check_interval", [1.0, 2], ids=["once per epoch", "every 2 batches"])
def test_every_validation_keeps_its_own_plots_also_several_in_one_epoch(tmp_path, val_check_interval):
    """With ``trainer.val_check_interval`` the callback ran twice in one epoch and the second drawing
    found the first one's file: training stopped with FileExistsError (plots are never overwritten)."""
    torch.manual_seed(0)
    module = PoseEstimationModule(
        MatrixFisherNet(_Encoder(), IMAGE_SIZE, hidden=4), optimizer=functools.partial(torch.optim.Adam, lr=0.01),
        class_names=["a"], train_grid_level=1, val_grid_level=1, eval_grid_level=1, spread_grid_level=1,
    )  # fmt: skip
    count = _CountValidations()
    trainer = pl.Trainer(
        accelerator="cpu", devices=1, max_epochs=2, logger=False, enable_checkpointing=False,
        enable_progress_bar=False, enable_model_summary=False, num_sanity_val_steps=1,
        val_check_interval=val_check_interval, default_root_dir=tmp_path,
        callbacks=[SO3PlotCallback(every_n_epochs=1, n_images=1, level=1), count],
    )  # fmt: skip
    trainer.fit(module, datamodule=_Data())
    names = sorted(p.name for p in (tmp_path / "plots").iterdir())
    if val_check_interval == 1.0:
        assert count.steps == [5, 10] and names == ["epoch=000_image=0.png", "epoch=001_image=0.png"]
    else:  # after batches 2 and 4 of each epoch of 5
        assert count.steps == [2, 4, 7, 9]
        assert names == [f"epoch={e:03d}_step={s:06d}_image=0.png" for e, s in ((0, 2), (0, 4), (1, 7), (1, 9))]
