"""``python -m src.eval ckpt_path=...``: the test metrics and plots of a checkpoint (see conf/eval.yaml)."""

import hydra
from omegaconf import DictConfig

import image2sphere  # noqa: F401  (sets up the torchvision guard before Lightning is imported)
from image2sphere.training.command_line import check_command_line
from image2sphere.training.entry import entry_point
from image2sphere.training.resolvers import register_resolvers

register_resolvers()


@hydra.main(version_base="1.3", config_path="../conf", config_name="eval.yaml")
def main(cfg: DictConfig) -> None:
    from image2sphere.training.evaluate import evaluate  # Lightning and the networks: when a run starts (src/train.py)

    with entry_point():  # a refused value: one line, exit status 1; a failed start leaves no run directory
        evaluate(cfg)


if __name__ == "__main__":
    check_command_line("eval.yaml")  # a mistyped key or option: one line, before Hydra composes
    main()
