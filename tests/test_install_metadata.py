"""The install rule: pyproject.toml asks for torch and torchvision ranges, constraints/cpu.txt pins the CPU install.

* ``pip install -e .`` must keep a torch that is already installed (a GPU machine's CUDA build), so
  pyproject.toml never pins torch or torchvision with ``==``; it gives a lower bound.
* The exact versions of the CPU-only install live in constraints/cpu.txt, which ``.ci/run`` and the
  README's "Install" section install with; any ``torch==``/``torchvision==`` that .ci/run, the README
  or the CI workflow still names is that pin.
* The pins satisfy pyproject.toml's ranges (else the package's install would replace the pinned torch),
  and each torchvision is the release made for its torch (torchvision 0.N+15 goes with torch 2.N).
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from packaging.requirements import Requirement
from packaging.version import Version

tomllib = pytest.importorskip("tomllib")  # Python 3.11+

REPO = Path(__file__).resolve().parents[1]
CONSTRAINTS = "constraints/cpu.txt"
PINNED = ("torch", "torchvision")


def project_requirements() -> dict[str, Requirement]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    requirements = [Requirement(r) for r in project["dependencies"]]
    return {r.name.lower(): r for r in requirements}


def cpu_pins() -> dict[str, Version]:
    pins = {}
    for line in (REPO / CONSTRAINTS).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        requirement = Requirement(line)
        specs = list(requirement.specifier)
        assert len(specs) == 1 and specs[0].operator == "==", f"{CONSTRAINTS}: {line!r} is not an exact pin"
        pins[requirement.name.lower()] = Version(specs[0].version)
    return pins


def pip_installs(text: str) -> list[list[str]]:
    """The arguments after ``pip install`` of each non-comment line that runs it."""
    out = []
    for line in text.splitlines():
        if line.lstrip().startswith("#") or "pip install" not in line:
            continue
        words = shlex.split(line)
        at = words.index("install")
        out.append(words[at + 1 :])
    return out


def install_section() -> str:
    readme = (REPO / "README.md").read_text()
    match = re.search(r"^## Install\n(.*?)(?=^## )", readme, re.S | re.M)
    assert match, "README.md has no '## Install' section"
    return match.group(1)


def uses_constraints(args: list[str]) -> bool:
    return any(a in ("-c", "--constraint") and b == CONSTRAINTS for a, b in zip(args, args[1:], strict=False))


def test_pyproject_asks_for_torch_and_torchvision_ranges_not_pins():
    requirements = project_requirements()
    for name in PINNED:
        assert name in requirements, f"pyproject.toml no longer names {name}"
        operators = {spec.operator for spec in requirements[name].specifier}
        assert not operators & {"==", "===", "~="}, f"pyproject.toml pins {requirements[name]}: give a range"
        assert ">=" in operators, f"pyproject.toml gives {name} no lower bound: {requirements[name]}"


def test_lower_bounds_pair_torchvision_with_its_torch():
    requirements = project_requirements()
    lower = {n: Version(s.version) for n in PINNED for s in requirements[n].specifier if s.operator == ">="}
    assert lower["torch"].major == 2 and lower["torchvision"].major == 0
    assert lower["torchvision"].minor == lower["torch"].minor + 15, lower


def test_cpu_constraints_pin_a_matching_pair_inside_the_ranges():
    pins = cpu_pins()
    assert set(pins) == set(PINNED), f"{CONSTRAINTS} pins {sorted(pins)}, not exactly {PINNED}"
    assert pins["torch"].major == 2 and pins["torchvision"].minor == pins["torch"].minor + 15, pins
    requirements = project_requirements()
    for name, version in pins.items():
        # the package's own install must keep the pinned version
        assert requirements[name].specifier.contains(version, prereleases=True), (name, version, requirements[name])


def test_ci_installs_torch_with_the_constraints_file_first():
    installs = pip_installs((REPO / ".ci" / "run").read_text())
    assert installs, ".ci/run installs nothing"
    first, package = installs[0], next((i for i, args in enumerate(installs) if "-e" in args), None)
    assert uses_constraints(first) and set(first) - {"-c", "--constraint", CONSTRAINTS} == set(PINNED), (
        f".ci/run's first install must be torch and torchvision with -c {CONSTRAINTS}: {first}"
    )
    assert package is not None and package > 0, f".ci/run must install the package after torch: {installs}"


def test_readme_install_section_uses_the_constraints_file():
    section = install_section()
    installs = pip_installs(section)
    torch_installs = [args for args in installs if set(PINNED) <= set(args)]
    assert torch_installs, f"README's Install section shows no torch install: {installs}"
    assert all(uses_constraints(args) for args in torch_installs), torch_installs
    assert (REPO / CONSTRAINTS).is_file()


@pytest.mark.parametrize("path", ["README.md", ".ci/run", ".github/workflows/ci.yml"])
def test_every_named_pin_is_the_constraints_pin(path):
    """Wherever these files still write ``torch==X`` or ``torchvision==Y`` (a comment, a sentence), it is the pin."""
    file = REPO / path
    if not file.is_file():
        pytest.skip(f"{path} is not in this checkout")
    pins = cpu_pins()
    for name, version in re.findall(r"\b(torch|torchvision)\s*==\s*([0-9][0-9A-Za-z.+]*)", file.read_text()):
        assert Version(version) == pins[name], f"{path} names {name}=={version}; {CONSTRAINTS} pins {pins[name]}"
