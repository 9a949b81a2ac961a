"""The per-run metrics table (``src.train`` and ``src.eval`` print it, ``metrics.md`` holds it): every metric
of ``metrics.json`` is shown, in a fixed order, a metric a run lacks reads ``n/a`` (never 0), and the
timings stay out of the headline columns."""

from __future__ import annotations

import pytest

from image2sphere.reporting import format_metrics_markdown, format_metrics_table
from image2sphere.reporting.metrics_table import metric_layout

CLASSES = ["cube", "cone"]


def flow_metrics() -> dict[str, float]:
    """A metrics.json as a closed-form family with a recalibration writes it (rotation_flow, matrix_fisher...),
    plus a metric of a method of one's own (``my_score``, only for the cube) and the timings."""
    metrics = {"n_images": 6.0, "loss": 3.25, "temperature": 0.5, "train_seconds": 12.34, "test_seconds": 1.5,
               "recalibration_seconds": 0.25}  # fmt: skip
    for key, value in {"log_likelihood": 1.0, "spread_deg": 20.0, "calibration_ece": 0.1, "acc15": 0.5, "acc30": 0.75,
                       "median_error_deg": 15.0, "log_likelihood_exact": 1.25, "log_likelihood_calibrated": 1.5,
                       "calibration_ece_calibrated": 0.05, "hdr_coverage_10": 0.125, "hdr_coverage_90": 0.875,
                       "hdr_coverage_10_calibrated": 0.1, "hdr_coverage_90_calibrated": 0.9}.items():  # fmt: skip
        metrics[key] = value
        metrics[f"{key}/cube"], metrics[f"{key}/cone"] = value + 1.0, value - 1.0
    metrics["my_score/cube"] = 7.0
    return metrics


def _cells(line: str) -> list[str]:
    return line.split()


def test_every_metric_of_a_closed_form_family_is_in_the_table_in_a_fixed_order():
    lines = format_metrics_table(flow_metrics(), CLASSES).splitlines()
    header = [t.strip() for t in lines[0].split("  ") if t.strip()]
    assert header == ["class", "log lik.", "spread", "ECE", "acc@15", "acc@30", "med.err", "LL recal.", "ECE recal.",
                      "LL exact", "my_score"]  # fmt: skip
    assert [_cells(line) for line in lines[1:]] == [
        ["cube", "2.000", "21.00", "1.100", "1.500", "1.750", "16.00", "2.500", "1.050", "2.250", "7.000"],
        ["cone", "0.000", "19.00", "-0.900", "-0.500", "-0.250", "14.00", "0.500", "-0.950", "0.250", "n/a"],
        ["mean", "1.000", "20.00", "0.100", "0.500", "0.750", "15.00", "1.500", "0.050", "1.250", "n/a"],
    ]
    # each column's cells end where its title ends
    ends = {line.index(cell) + len(cell) for line in lines[1:] for cell in ["7.000"] if cell in line}
    assert ends == {lines[0].index("my_score") + len("my_score")}
    assert "seconds" not in lines[0] and "hdr" not in lines[0].lower() and "loss" not in lines[0]


def test_details_show_the_coverage_the_run_numbers_and_the_timings_after_the_table():
    text = format_metrics_table(flow_metrics(), CLASSES, details=True)
    main, coverage, calibrated, numbers = text.split("\n\n")
    assert main == format_metrics_table(flow_metrics(), CLASSES)
    title, header, *rows = coverage.splitlines()
    assert title.startswith("HDR coverage (") and header.split() == ["class", "10%", "90%"]
    assert [r.split() for r in rows] == [["cube", "1.125", "1.875"], ["cone", "-0.875", "-0.125"],
                                         ["mean", "0.125", "0.875"]]  # fmt: skip
    assert calibrated.splitlines()[0] == "HDR coverage after recalibration:"
    assert calibrated.splitlines()[-1].split() == ["mean", "0.100", "0.900"]
    assert numbers.splitlines() == ["loss 3.250, temperature 0.500, test images 6",
                                    "seconds: train 12.3, recalibration 0.2, test 1.5"]  # fmt: skip


def test_a_point_regressor_reads_na_and_has_no_details_it_lacks():
    metrics = {"acc15": 0.5, "acc30": 0.75, "median_error_deg": 15.0, "acc15/cube": 0.5, "n_images": 6.0,
               "loss": 1.0, "test_seconds": 2.0}  # fmt: skip
    markdown = format_metrics_markdown(metrics, CLASSES, details=True)
    assert markdown.splitlines() == [
        "| class | log lik. | spread | ECE | acc@15 | acc@30 | med.err |",
        "|---|---|---|---|---|---|---|",
        "| cube | n/a | n/a | n/a | 0.500 | n/a | n/a |",
        "| mean | n/a | n/a | n/a | 0.500 | 0.750 | 15.00 |",
        "",
        "loss 1.000, test images 6",
        "seconds: test 2.0",
    ]
    assert format_metrics_markdown(metrics, CLASSES) == "\n".join(markdown.splitlines()[:4]) + "\n"


@pytest.mark.parametrize(
    ("key", "part"),
    [("log_likelihood_exact", "main"), ("my_score", "main"), ("spread_deg_calibrated", "main"),
     ("hdr_coverage_30", "coverage"), ("hdr_coverage_30_calibrated", "coverage_calibrated"),
     ("temperature", "numbers"), ("skipped_images", "numbers"), ("data_seconds", "timings")],
)  # fmt: skip
def test_every_key_has_one_place(key, part):
    layout = metric_layout([key, f"{key}/cube"])
    places = [name for name in ("main", "coverage", "coverage_calibrated", "numbers", "timings")
              if key in [k for k, _, _ in getattr(layout, name)]]  # fmt: skip
    assert places == [part]
