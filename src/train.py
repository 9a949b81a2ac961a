"""Train (and test) a pose network: ``python -m src.train [overrides]`` from the repository root.

Everything is configured in ``conf/train.yaml`` and its groups; see the README for examples.
"""

import hydra
from omegaconf import DictConfig

# image2sphere (imported first by this line) makes torchvision and Lightning importable on CPU torch.
from image2sphere.training.command_line import check_command_line
from image2sphere.training.entry import entry_point
from image2sphere.training.resolvers import register_resolvers

register_resolvers()


@hydra.main(version_base="1.3", config_path="../conf", config_name="train.yaml")
def main(cfg: DictConfig) -> float | None:
    # Lightning and the networks are imported when a run starts: not for --help, a refused command line, or
    # the loader workers that run this module again
    from image2sphere.training.pipeline import train

    with entry_point():  # a refused value: one line, exit status 1; a failed start leaves no run directory
        metrics = train(cfg)
    metric = cfg.get("optimized_metric")
    return metrics.get(metric) if metric else None


if __name__ == "__main__":
    check_command_line("train.yaml")  # a mistyped key or option: one line, before Hydra composes
    main()
