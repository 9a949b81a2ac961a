"""Run discovery (:func:`image2sphere.reporting.find_runs`) of a resumed run: what ``src.tables`` reads is what
the run really trained (``resumed_config.yaml``), with the original run's group choices and overrides plus
those of the resume's command line that changed a value; ``ckpt_path`` is no setting.

Hand-written run directories (the files a sweep job and its resume leave), then the slow test: a real
tiny sweep whose jobs are resumed, in its true rows of Table 7 and of the sweep's own table."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import yaml
from src.tables import main as tables_main

from image2sphere.reporting import (
    build_sweep_table,
    build_table,
    counted_runs,
    find_runs,
    load_layouts,
    sweep_to_markdown,
)

LAYOUTS = load_layouts()
CHOICES = {"table": None, "dataset": "symsol_rendered", "model": "i2s", "encoder": "resnet18", "logger": "csv",
           "trainer": "default", "hydra/sweeper": "basic"}  # fmt: skip
METRICS = {"acc15": 0.5, "acc30": 0.6, "median_error_deg": 40.0, "log_likelihood": 1.0}


def write_checkpoint(path: Path, epochs: int, steps: int | None = None, mid_epoch: bool = False) -> Path:
    """A checkpoint as Lightning writes it, with only the parts that say how far training got: ``epochs``
    whose batches were all done (3 batches each), written at an epoch's end or ``mid_epoch`` (after 1 batch
    of the next)."""
    import torch

    batches = {"current": {"processed": 1 if mid_epoch else 3}, "is_last_batch": not mid_epoch}
    loops = {"fit_loop": {"epoch_progress": {"current": {"processed": epochs, "completed": max(epochs - 1, 0)}},
                          "epoch_loop.batch_progress": batches}}  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {"epoch": max(epochs - 1, 0), "global_step": 3 * epochs if steps is None else steps, "loops": loops,
             "state_dict": {"w": torch.zeros(2)}}  # fmt: skip
    torch.save(state, path)
    return path


def write_run(
    run: Path, config: dict, overrides: list[str], choices: dict | None = None, mode: str = "RUN",
    resumed: dict | None = None, metrics: dict | None = METRICS, cwd: Path | None = None,
) -> Path:  # fmt: skip
    """A run directory as Hydra and src.train leave it: ``resumed`` is the resumed_config.yaml of a resume."""
    (run / ".hydra").mkdir(parents=True)
    base = {
        "seed": 0,
        "lmax": 6,
        "ckpt_path": None,
        "trainer": {"max_epochs": 5},
        "model": {"net": {"lmax": "${lmax}"}},
    }
    (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump({**base, **config}))
    runtime = {"choices": {**CHOICES, **(choices or {})}, "cwd": str(cwd or run.parent), "output_dir": str(run)}
    hydra = {"hydra": {"mode": mode, "runtime": runtime, "overrides": {"task": overrides}}}
    (run / ".hydra" / "hydra.yaml").write_text(yaml.safe_dump(hydra))
    (run / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump(overrides))
    if resumed is not None:
        (run / "resumed_config.yaml").write_text(yaml.safe_dump({**base, **resumed}))
    effective = {**base, **(resumed if resumed is not None else config)}
    write_checkpoint(run / "checkpoints" / "last.ckpt", effective["trainer"]["max_epochs"])  # trained to its end
    if metrics is not None:
        (run / "metrics.json").write_text(json.dumps(metrics))
    return run


def origin_and_resume(tmp_path: Path, resume_overrides: list[str], resumed: dict, **resume_kw) -> tuple[Path, Path]:
    """Job 1 of a table=small/table7 sweep (lmax 4, 2 epochs), and its resume in ``tmp_path/resumed``."""
    origin = write_run(tmp_path / "sweep" / "1", {"lmax": 4, "trainer": {"max_epochs": 2}}, ["lmax=4"],
                       {"table": "small/table7", "hydra/sweeper": "table"}, mode="MULTIRUN", metrics=None)  # fmt: skip
    ckpt = origin / "checkpoints" / "last.ckpt"
    config = {"ckpt_path": str(ckpt), **{k: yaml.safe_load(v) for k, v in (o.split("=", 1) for o in resume_overrides)
                                          if "." not in k}}  # fmt: skip
    resume = write_run(tmp_path / "resumed", config, [f"ckpt_path={ckpt}", *resume_overrides],
                       resumed={"ckpt_path": str(ckpt), **resumed}, **resume_kw)  # fmt: skip
    return origin, resume


def test_a_resumed_run_is_read_as_what_it_trained(tmp_path):
    _, resume = origin_and_resume(tmp_path, ["trainer.max_epochs=3"], {"lmax": 4, "trainer": {"max_epochs": 3}})
    (run,), unfinished = find_runs([tmp_path / "resumed"])
    assert unfinished == []
    assert run.get("lmax") == 4 and run.get("model.net.lmax") == 4  # resumed_config.yaml's, not lmax 6; resolved
    assert run.get("table") == "small/table7" and run.get("logger") == "csv"  # the original's choices, its own logger
    assert run.get("hydra/sweeper") == "basic"  # Hydra's own groups are the resumed run's
    # the original's overrides, plus the one that changed a value; ckpt_path is none
    assert run.overrides == ["lmax=4", "trainer.max_epochs=3"]
    assert run.resumed_from == tmp_path / "sweep" / "1" / "checkpoints" / "last.ckpt" and run.notes == []
    filled = build_table("table7", LAYOUTS["table7"], [run], dataset="symsol_rendered")
    rows = zip(filled.layout["rows"], filled.cells, strict=True)
    assert [row["label"] for row, cells in rows if any(c.runs for c in cells)] == ["L=4"]


def test_an_override_that_changed_nothing_is_no_setting_and_a_named_group_is_the_resumes(tmp_path):
    # trainer.max_epochs=2 is what the original ran; dataset=symsol1 replaces the checkpoint's dataset
    _, resume = origin_and_resume(
        tmp_path, ["trainer.max_epochs=2", "dataset=symsol1"], {"lmax": 4, "trainer": {"max_epochs": 2}},
        choices={"dataset": "symsol1", "model": "i2s"},
    )  # fmt: skip
    (run,), _ = find_runs([resume])
    assert run.overrides == ["lmax=4", "dataset=symsol1"]
    assert run.get("dataset") == "symsol1" and run.get("table") == "small/table7"


def test_a_resume_of_a_resume_and_a_relative_checkpoint_path_follow_back_to_the_original(tmp_path):
    origin, first = origin_and_resume(tmp_path, ["trainer.max_epochs=3"], {"lmax": 4, "trainer": {"max_epochs": 3}})
    relative = Path("resumed") / "checkpoints" / "last.ckpt"  # relative to where the second resume was started
    overrides = [f"ckpt_path={relative}", "trainer.max_epochs=4"]
    second = write_run(tmp_path / "again", {"ckpt_path": str(relative)}, overrides, cwd=tmp_path,
                       resumed={"ckpt_path": str(relative), "lmax": 4, "trainer": {"max_epochs": 4}})  # fmt: skip
    (run,), _ = find_runs([second])
    assert run.get("lmax") == 4 and run.get("table") == "small/table7"
    assert run.overrides == ["lmax=4", "trainer.max_epochs=4"], run.overrides
    assert run.resumed_from == first / "checkpoints" / "last.ckpt"


def test_a_resume_whose_original_is_gone_keeps_its_values_and_says_what_is_unknown(tmp_path, capsys):
    ckpt = tmp_path / "copied" / "last.ckpt"  # a checkpoint copied out of its run directory
    write_run(tmp_path / "resumed", {"ckpt_path": str(ckpt)}, [f"ckpt_path={ckpt}", "trainer.max_epochs=3"],
              resumed={"ckpt_path": str(ckpt), "lmax": 4, "trainer": {"max_epochs": 3}})  # fmt: skip
    (run,), _ = find_runs([tmp_path / "resumed"])
    assert run.get("lmax") == 4 and run.get("logger") == "csv"  # its values and its own groups
    assert run.get("model") is None and run.get("dataset") is None  # unknown, not the resume's defaults
    assert run.overrides == ["trainer.max_epochs=3"]
    (note,) = run.notes
    assert str(ckpt) in note and "model" in note and "dataset" in note and "unknown" in note
    assert tables_main([str(tmp_path / "resumed"), "--table", "table7", "--out", str(tmp_path / "out")]) == 0
    err = capsys.readouterr().err
    assert f"note: {tmp_path / 'resumed'}: resumed from {ckpt}" in err


def test_a_resume_whose_original_is_unreadable_says_so(tmp_path):
    """Quick. The original run directory is there but its ``.hydra/config.yaml`` is not YAML: the note says the
    directory is unreadable (and which), not that no directory holds the checkpoint."""
    origin, resume = origin_and_resume(tmp_path, ["trainer.max_epochs=3"], {"lmax": 4, "trainer": {"max_epochs": 3}})
    (origin / ".hydra" / "config.yaml").write_text("lmax: [unclosed\n")
    (run,), _ = find_runs([resume])
    (note,) = run.notes
    assert f"{origin}, is unreadable" in note and "no run directory" not in note, note
    assert run.get("table") is None and run.get("lmax") == 4  # unknown choices; its own values


@pytest.mark.parametrize(("override", "key"), [
    ("+a.b=1", "a.b"), ("++a.b=1", "a.b"), ("~trainer.devices", "trainer.devices"), ("dataset=symsol1", "dataset"),
    ("dataset@data=symsol1", "dataset"), ("hydra/sweeper=table", "hydra/sweeper"), ("seed=0,1", "seed"),
    ("model.net.tags=[a,b]", "model.net.tags"), ("key='a=b'", "key"), ("not an override", "not an override"),
])  # fmt: skip
def test_override_keys_are_hydras(override, key):
    """Quick. The key or group an override sets, as Hydra's own parser reads it (``@package`` left out)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from image2sphere.config_text import override_key

    assert override_key(override) == key
    if key != override:  # a text Hydra parses: the same key as Hydra's parser gives
        assert OverridesParser.create().parse_override(override).key_or_group == key


def test_config_values_follow_every_interpolation_omegaconf_resolves(tmp_path):
    """Quick. A run's config value is OmegaConf's: a plain ``${key}``, one inside a string, one through
    ``oc.select``; one of a resolver this process does not have (a plugin's) reads as absent."""
    config = {"lmax": 4, "name": "l${lmax}", "alias": "${oc.select:lmax,0}", "out": "${a_plugins_resolver:x}"}
    (run,), _ = find_runs([write_run(tmp_path / "run", config, [])])
    assert (run.get("name"), run.get("alias"), run.get("out", "absent")) == ("l4", 4, "absent")
    assert run.get("model.net") == {"lmax": 4}


def test_two_resumed_sweep_jobs_differ_in_lmax_not_in_ckpt_path(tmp_path):
    for job, lmax in ((0, 2), (1, 4)):
        origin = write_run(tmp_path / "sweep" / str(job), {"lmax": lmax, "trainer": {"max_epochs": 1}},
                           [f"lmax={lmax}", "trainer.max_epochs=1"], mode="MULTIRUN", metrics=None)  # fmt: skip
        ckpt = origin / "checkpoints" / "last.ckpt"
        resumed = {"ckpt_path": str(ckpt), "lmax": lmax, "trainer": {"max_epochs": 2}}
        write_run(tmp_path / "resumed" / f"job{job}", {"ckpt_path": str(ckpt)},
                  [f"ckpt_path={ckpt}", "trainer.max_epochs=2"], resumed=resumed)  # fmt: skip
    found, _ = find_runs([tmp_path / "resumed"])
    table = build_sweep_table(found)
    assert table.keys == ["lmax"], table.keys
    assert sorted(r.overrides[0] for r in found) == ["lmax=2", "lmax=4"]
    assert all(r.overrides[1:] == ["trainer.max_epochs=2"] for r in found)


# ------------------------------------------------------------------------------- a real sweep, resumed
@pytest.mark.slow
def test_resumed_jobs_of_a_real_sweep_land_in_their_rows(tmp_path):
    """``table=small/table7`` with ``lmax=2,4`` (two jobs of one batch each), each job resumed with
    ``ckpt_path=`` and one more epoch, as the README shows (no lmax on the resume's command line): Table 7
    has the lmax-4 resume in row L=4, and the sweep table of the two resumes has an lmax column."""
    from conftest import ENV, REPO, run_module, run_train

    data, one_batch = tmp_path / "data", ["trainer.limit_train_batches=1", "trainer.limit_val_batches=1"]
    sweep = tmp_path / "sweep"
    run_train(["table=small/table7", "lmax=2,4", "trainer.max_epochs=1", "logger=none",
               "recalibration=off", f"hydra.sweep.dir={sweep}", *one_batch], data, tmp_path / "logs")  # fmt: skip
    resumed = tmp_path / "resumed"
    for job in (0, 1):
        ckpt = sweep / str(job) / "checkpoints" / "last.ckpt"
        command = [sys.executable, "-m", "src.train", f"ckpt_path={ckpt}", "trainer.max_epochs=2",
                   f"hydra.run.dir={resumed / f'job{job}'}", f"paths.data_dir={data}", "logger=none",
                   "recalibration=off", "trainer.accelerator=cpu", "callbacks.progress_bar.refresh_rate=0",
                   *one_batch]  # fmt: skip
        run_module(command, env=ENV, cwd=REPO)
    job1 = resumed / "job1"
    assert yaml.safe_load((job1 / ".hydra" / "config.yaml").read_text())["lmax"] == 6  # the command's default
    assert yaml.safe_load((job1 / "resumed_config.yaml").read_text())["lmax"] == 4  # what it trained

    proc = run_module([sys.executable, "-m", "src.tables", str(job1), "--table", "table7", "--dataset",
                       "symsol_rendered", "--out", str(tmp_path / "t7")])  # fmt: skip
    rows = {line.split("|")[1].strip(): line for line in proc.stdout.splitlines() if "| ours" in line}
    assert "(1 run)" in rows["L=4"] and all("(1 run)" not in rows[k] for k in rows if k != "L=4"), proc.stdout
    acc15 = json.loads((job1 / "metrics.json").read_text())["acc15"]
    assert f"| {acc15:.3f} |" in rows["L=4"]

    found, unfinished = find_runs([resumed])
    assert unfinished == [] and {r.get("table") for r in found} == {"small/table7"}
    markdown = sweep_to_markdown(build_sweep_table(found))
    header = next(line for line in markdown.splitlines() if line.startswith("| "))
    assert header.split("|")[1].strip() == "lmax" and "ckpt_path" not in markdown, markdown
    main_table = markdown.split("\n\n")[2]  # after the heading and the explanation; further tables follow
    lmax_cells = [line.split("|")[1].strip() for line in main_table.splitlines() if line.startswith("| ")][1:]
    assert lmax_cells == ["2", "4"], markdown


def test_a_left_over_start_is_told_apart_from_a_run_that_stopped(tmp_path):
    """A directory with only ``.hydra/`` and the log (a start refused by an earlier version, or a run still
    starting) is listed as unfinished with what it holds; a run that stopped after writing a checkpoint is not."""
    started = write_run(tmp_path / "runs" / "a", {}, ["lmax=-1"], metrics=None)
    (started / "checkpoints" / "last.ckpt").unlink()
    (started / "checkpoints").rmdir()
    (started / "train.log").write_text("")
    write_run(tmp_path / "runs" / "b", {}, [], metrics=None)  # stopped with its checkpoint
    runs, unfinished = find_runs([tmp_path / "runs"])
    reasons = {u.path.name: u.reason for u in unfinished}
    assert runs == [] and sorted(reasons) == ["a", "b"]
    assert "only .hydra/ and the log" in reasons["a"] and "only .hydra/" not in reasons["b"]
    assert reasons["b"].startswith("no metrics.json")


# ------------------------------------------------------------------------------------- finished or not
def test_which_runs_with_metrics_are_finished(tmp_path):
    """A run counts when it trained to its configured end and tested the whole test set; what each of the
    others is, as src.tables lists it."""
    root = tmp_path / "runs"
    write_run(root / "done", {}, [])  # 5 epochs of 5
    write_run(root / "smoke", {"trainer": {"max_epochs": 5, "fast_dev_run": True}}, [])
    write_run(root / "part_test", {"trainer": {"max_epochs": 5, "limit_test_batches": 2}}, [])
    write_run(root / "tenth_test", {"trainer": {"max_epochs": 5, "limit_test_batches": 0.1}}, [])
    write_run(root / "budget", {"trainer": {"max_epochs": 5, "limit_train_batches": 2, "limit_test_batches": 1.0}}, [])
    write_checkpoint(write_run(root / "stopped", {}, []) / "checkpoints" / "last.ckpt", 2)
    write_checkpoint(write_run(root / "mid_epoch", {}, []) / "checkpoints" / "last.ckpt", 2, mid_epoch=True)
    steps = write_run(root / "steps", {"trainer": {"max_epochs": 5, "max_steps": 4}}, [])
    write_checkpoint(steps / "checkpoints" / "last.ckpt", 1, steps=4)  # ended at max_steps, as configured
    tested = write_run(root / "test_only", {"train": False}, [])  # train=false: only tests a checkpoint
    write_checkpoint(tested / "checkpoints" / "last.ckpt", 1)
    (write_run(root / "no_ckpt", {}, []) / "checkpoints" / "last.ckpt").unlink()  # nothing says it stopped
    broken = write_run(root / "broken_ckpt", {}, [])
    (broken / "checkpoints" / "last.ckpt").write_bytes(b"PK\x03\x04 truncated")
    runs, unfinished = find_runs([root])
    reasons = {r.path.name: r.incomplete for r in runs}
    assert unfinished == [] and reasons == {
        "done": None,
        "smoke": "fast_dev_run",
        "part_test": "limit_test_batches=2: tested on at most 2 batches of the test set",
        "tenth_test": "limit_test_batches=0.1: tested on 10% of the batches of the test set",
        "budget": None,
        "stopped": "unfinished: stopped after epoch 2 of 5",
        "mid_epoch": "unfinished: stopped during epoch 3 of 5",
        "steps": None,
        "test_only": None,
        "no_ckpt": None,
        "broken_ckpt": None,
    }
    (note,) = next(r for r in runs if r.path.name == "broken_ckpt").notes
    assert "last.ckpt is not readable" in note and "unknown" in note
    counted, left_out = counted_runs(runs)
    assert {r.path.name for r in left_out} == {"smoke", "part_test", "tenth_test", "stopped", "mid_epoch"}
    assert counted_runs(runs, include_unfinished=True) == (runs, [])


def test_a_resumed_run_is_finished_by_its_own_schedule(tmp_path):
    """A resume reads its epochs against resumed_config.yaml; one that had nothing left to train (no checkpoint
    of its own) is read by the checkpoint it started from."""
    _, resume = origin_and_resume(tmp_path, ["trainer.max_epochs=3"], {"lmax": 4, "trainer": {"max_epochs": 3}})
    write_checkpoint(resume / "checkpoints" / "last.ckpt", 2)  # .hydra/config.yaml's 5 epochs are not its own
    (run,), _ = find_runs([resume])
    assert run.incomplete == "unfinished: stopped after epoch 2 of 3"
    (resume / "checkpoints" / "last.ckpt").unlink()
    write_checkpoint(run.resumed_from, 3)  # the original's checkpoint: 3 epochs
    (run,), _ = find_runs([resume])
    assert run.incomplete is None


def test_runs_not_counted_are_listed_and_counted_only_when_asked(tmp_path, capsys):
    sweep = tmp_path / "sweep"
    for job, (lmax, acc) in enumerate(((2, 0.2), (2, 0.4), (4, 0.8))):
        metrics = {**METRICS, "acc15": acc}
        write_run(sweep / str(job), {"lmax": lmax}, [f"lmax={lmax}", f"seed={job}"], mode="MULTIRUN", metrics=metrics)
    stopped = sweep / "1"
    write_checkpoint(stopped / "checkpoints" / "last.ckpt", 1)
    assert tables_main([str(sweep), "--out", str(tmp_path / "a")]) == 0
    printed = capsys.readouterr()
    header, *rows = [line.split(" | ") for line in printed.out.splitlines() if line.startswith("| ")][:3]
    acc15, runs = header.index("acc@15"), header.index("runs |")
    assert [(r[0], r[acc15], r[runs]) for r in rows] == [("| 2", "0.200", "1 |"), ("| 4", "0.800", "1 |")]
    assert f"- not counted: `{stopped}` (unfinished: stopped after epoch 1 of 5)" in printed.out
    assert f"not counted: {stopped} (unfinished: stopped after epoch 1 of 5)" in printed.err.splitlines()
    assert "### Sweep: 2 finished runs, 2 settings" in printed.out
    assert tables_main([str(sweep), "--out", str(tmp_path / "b"), "--include-unfinished"]) == 0
    printed = capsys.readouterr()
    header, *rows = [line.split(" | ") for line in printed.out.splitlines() if line.startswith("| ")][:3]
    assert [(r[0], r[acc15], r[runs]) for r in rows] == [("| 2", "0.300 ± 0.141", "2 (1 unfinished) |"),
                                                            ("| 4", "0.800", "1 |")]  # fmt: skip
    assert "### Sweep: 2 finished runs and 1 unfinished, 2 settings" in printed.out
    assert f"- counted although unfinished: `{stopped}` (unfinished: stopped after epoch 1 of 5)" in printed.out
    assert "not counted" not in printed.out + printed.err
