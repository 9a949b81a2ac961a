"""``python -m src.predict ckpt_path=... image=...``: modes and plot for one image (see conf/predict.yaml)."""

import hydra
from omegaconf import DictConfig

import image2sphere  # noqa: F401  (sets up the torchvision guard before Lightning is imported)
from image2sphere.training.command_line import check_command_line
from image2sphere.training.entry import entry_point
from image2sphere.training.resolvers import register_resolvers

register_resolvers()


@hydra.main(version_base="1.3", config_path="../conf", config_name="predict.yaml")
def main(cfg: DictConfig) -> None:
    # the model and its checks: imported when a prediction starts (src/train.py)
    from image2sphere.inference import predict
    from image2sphere.training.run_config import check_predict_config

    with entry_point():  # a refused value: one line, exit status 1; a failed start leaves no run directory
        check_predict_config(cfg)
        predict(
            ckpt_path=cfg.ckpt_path, image=cfg.image, class_index=cfg.class_index, output=cfg.output, top_k=cfg.top_k,
            level=cfg.eval_grid_level, radius_deg=cfg.radius_deg, threshold=cfg.threshold, device=cfg.device,
            recalibration=cfg.get("recalibration", "auto"),
        )  # fmt: skip


if __name__ == "__main__":
    check_command_line("predict.yaml")  # a mistyped key or option: one line, before Hydra composes
    main()
