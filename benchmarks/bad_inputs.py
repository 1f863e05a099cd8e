"""How the command line meets bad input: a catalogue of mistakes per command, each run as
``python -m toolkit ...`` in a fresh temporary folder on the coarse sizes.

Each row records the exit code, the ``error:`` line, whether the error is *clear* and the wall
time to the error. The rule for *clear* is mechanical:

- the exit code is 2;
- stderr holds no ``Traceback``;
- exactly one line of stderr contains ``error:`` (the toolkit's ``error: ...`` or argparse's
  ``toolkit ...: error: ...``);
- that line names what was refused: it contains at least one of the case's tokens (the file's
  name, the key or the value the user gave, or the option; an option ``--plans`` also matches
  its word ``plans``, case and ``_``/``-`` aside).

``names_option`` says, for a case whose input is a command-line option, whether the line holds
the option as typed (``--plans``): the command line's own terms. ``left_files`` says whether the
failed command left anything in its folder (a check made after something was written).

The time to the error is compared with the command's import time (a subprocess importing the
CLI and the workflow modules the command uses, best of three): a row is *slow* when its time
exceeds three times that, i.e. more than importing the modules, parsing and reading the inputs
would take. On the coarse sizes a whole simulation takes about a second, so the flag is a weak
detector of work done before the check; ``left_files`` is the other.

The fixtures (a coarse face mesh, static and impact databases and models) are built once into
``benchmarks/work/bad_inputs/fixtures`` (about 20 s).

    python benchmarks/bad_inputs.py                 # the catalogue, ~2 min
    python benchmarks/bad_inputs.py --only static   # the commands whose name starts so (a trial)
    python benchmarks/bad_inputs.py --interrupts    # Ctrl-C in each long and short command, then rerun, ~9 min

``--interrupts`` runs each long command (``static database``, ``impact database``, ``static
train``, ``impact train``, tiny) once to its end, then afresh once per interrupt time (0.5 s, and
30, 60 and 90 % of the uninterrupted run), sends Ctrl-C (SIGINT to its process group) at that
time, counts the finished simulations (records in the database and its shards) or epochs (the
checkpoint's), reruns the same command (a training with ``--resume``, which its refusal names)
and counts again: nothing is lost when the count after is at least the count before, and the
rerun completes the job when it exits 0 with the uninterrupted run's count.

``--interrupts`` also interrupts each short command (``simulate``, ``predict``, ``evaluate`` of
both workflows; ``bad_inputs_interrupts_short.csv``) at the same fractions of its run and
records what its output folder holds: nothing, a complete result, a result marked as
interrupted, or partial files (which must not happen), and whether the same command rerun into
it completes.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
from _provenance import RESULTS, WORK, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/__main__.py", "toolkit/__init__.py", "toolkit/cli/", "toolkit/static/", "toolkit/impact/",
            "toolkit/common/")

FIXTURES = WORK / "bad_inputs" / "fixtures"
PY = sys.executable
#: coarse impact options (rigid ball, tet4): a bad input must be refused before any of it runs
IMPACT = ["--resolution", "coarse", "--order", "1", "--ball", "rigid"]
#: the quickest impact runs: explicit dynamics with mass scaling 100
EXPLICIT = ["--integrator", "explicit", "--mass-scaling", "100"]
#: modules each command imports before it can check its input
MODULES = {"simulate": "toolkit.cli, toolkit.{workflow}", "database": "toolkit.cli, toolkit.{workflow}",
           "train": "toolkit.cli, toolkit.{workflow}, toolkit.{workflow}.surrogate, torch",
           "evaluate": "toolkit.cli, toolkit.{workflow}, toolkit.{workflow}.surrogate, torch",
           "predict": "toolkit.cli, toolkit.{workflow}, toolkit.{workflow}.surrogate, torch",
           "phantom": "toolkit.cli, toolkit.static", "demo": "toolkit.cli, toolkit.static"}


def toolkit(*args: str, cwd: Path, timeout: float = 300) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.perf_counter()
    proc = subprocess.run([PY, "-m", "toolkit", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=timeout, env={**os.environ, "PYTHONWARNINGS": "default"})
    return proc, time.perf_counter() - t0


def build_fixtures() -> None:
    """Face mesh, two static databases (mucosa+lip and no sliding), two impact databases (with
    and without a held-out velocity) and a model of each workflow, all coarse and tiny."""
    FIXTURES.mkdir(parents=True, exist_ok=True)
    steps = [
        ("face.inp", ["phantom", "face-hex", "--resolution", "coarse", "--out", "face.inp"]),
        ("static.h5", ["static", "database", "--resolution", "coarse", "--plans", "3", "--workers", "0",
                       "--out", "static.h5"]),
        ("static_none.h5", ["static", "database", "--resolution", "coarse", "--plans", "3", "--seed", "5",
                            "--sliding", "none", "--workers", "0", "--out", "static_none.h5"]),
        ("smodel/model.pt", ["static", "train", "--data", "static.h5", "--epochs", "1", "--network", "tiny",
                             "--out", "smodel"]),
        ("impact.h5", ["impact", "database", *IMPACT, *EXPLICIT,
                       "--velocities", "30,40", "--held-out", "35", "--workers", "0", "--out", "impact.h5"]),
        ("imodel/model.pt", ["impact", "train", "--data", "impact.h5", "--epochs", "1", "--out", "imodel"]),
        ("impact_no_held.h5", ["impact", "database", *IMPACT, *EXPLICIT, "--velocities", "30",
                               "--held-out", "", "--workers", "0", "--out", "impact_no_held.h5"]),
    ]
    for target, args in steps:
        if not (FIXTURES / target).exists():
            proc, _ = toolkit(*args, cwd=FIXTURES)
            if proc.returncode != 0:
                raise RuntimeError(f"fixture {target}: {proc.stderr[-2000:]}")


# ----------------------------------------------------------------------------------------------
# the catalogue

GOOD_PLAN = "[lefort]\ntranslation_mm = [0.0, 4.0, -2.0]\n"


@dataclass
class Case:
    command: str  #: e.g. "static simulate"
    case: str  #: what is wrong, in a few words
    args: list[str]  #: after the command; "{F}" is the fixtures folder
    names: list[str]  #: tokens of which the error line must contain one
    files: dict[str, bytes | str] = field(default_factory=dict)  #: written into the folder first
    copy: list[str] = field(default_factory=list)  #: fixtures copied into the folder first


def _skull_scene() -> str:
    return ("duration = 0.9\nn_frames = 9\n[face]\nresolution = \"coarse\"\nsupport = \"skull\"\n"
            "[ball]\nrigid = true\nvelocity = 40.0\n[fidelity]\norder = 1\nintegrator = \"quasi-static\"\n")


def catalogue() -> list[Case]:
    binary = bytes(range(256)) * 8
    metres = "*NODE\n1, 0.0, 0.0, 0.0\n2, 0.001, 0.0, 0.0\n3, 0.0, 0.001, 0.0\n4, 0.0, 0.0, 0.001\n" \
             "*ELEMENT, TYPE=C3D4\n1, 1, 2, 3, 4\n"
    garbage = "*NODE\n1, 0.0, a, 0.0\n"
    mesh_cases = [
        ("missing mesh", ["--mesh", "nothere.inp", "--plan", "plan.toml"], ["nothere.inp"]),
        ("garbage mesh", ["--mesh", "garbage.inp", "--plan", "plan.toml"], ["garbage.inp"]),
        ("empty mesh", ["--mesh", "empty.inp", "--plan", "plan.toml"], ["empty.inp"]),
        ("binary mesh", ["--mesh", "binary.inp", "--plan", "plan.toml"], ["binary.inp"]),
        ("metres mesh", ["--mesh", "metres.inp", "--plan", "plan.toml"], ["metres.inp", "--units"]),
        ("unknown mesh suffix", ["--mesh", "face.xyz", "--plan", "plan.toml"], ["face.xyz"]),
    ]
    mesh_files = {"garbage.inp": garbage, "empty.inp": "", "binary.inp": binary, "metres.inp": metres,
                  "face.xyz": "1 2 3\n", "plan.toml": GOOD_PLAN}
    plans = {
        "syntax.toml": "[lefort]\ntranslation_mm = [0.0, 4.0\n",
        "typo.toml": "[lefort]\ntranslaton_mm = [0.0, 4.0, -2.0]\n",
        "segment.toml": "[lefrot]\ntranslation_mm = [0.0, 4.0, -2.0]\n",
        "large.toml": "[lefort]\ntranslation_mm = [0.0, 40.0, 0.0]\n",
        "nan.toml": "[lefort]\ntranslation_mm = [0.0, nan, 0.0]\n",
        "short.toml": "[lefort]\ntranslation_mm = [0.0, 4.0]\n",
        "plan.json": "{\"lefort\": {\"translation_mm\": [0, 4, \n",
    }
    plan_cases = [
        ("plan TOML syntax", ["--plan", "syntax.toml"], ["syntax.toml"]),
        ("plan key typo", ["--plan", "typo.toml"], ["translaton_mm"]),
        ("plan unknown segment", ["--plan", "segment.toml"], ["lefrot"]),
        ("plan out of range without --force", ["--plan", "large.toml"], ["--force"]),
        ("plan NaN", ["--plan", "nan.toml"], ["nan", "NaN"]),
        ("plan vector of two numbers", ["--plan", "short.toml"], ["translation_mm"]),
        ("plan JSON syntax", ["--plan", "plan.json"], ["plan.json"]),
        ("missing plan", ["--plan", "nothere.toml"], ["nothere.toml"]),
    ]
    out_cases = [
        ("--out an existing file", ["--out", "taken"], ["taken"]),
        ("--out under /proc", ["--out", "/proc/x"], ["/proc/x"]),
    ]
    out_files = {"taken": "x"}
    cases: list[Case] = []

    # static simulate
    cmd = "static simulate"
    base = ["--resolution", "coarse", "--no-preview"]
    for name, args, tok in mesh_cases:
        cases.append(Case(cmd, name, [*args, "--no-preview", "--out", "o"], tok, dict(mesh_files)))
    for name, args, tok in plan_cases:
        cases.append(Case(cmd, name, [*base, *args, "--out", "o"], tok, dict(plans)))
    for name, args, tok in out_cases:
        cases.append(Case(cmd, name, [*base, *args], tok, dict(out_files)))
    cases += [
        Case(cmd, "--increments 0", [*base, "--increments", "0", "--out", "o"], ["--increments", "0"]),
        Case(cmd, "--threads 0", [*base, "--threads", "0", "--out", "o"], ["--threads"]),
        Case(cmd, "--bone unknown segment", [*base, "--bone", "chin=b.stl", "--out", "o"], ["chin"]),
        Case(cmd, "--bone missing file", [*base, "--bone", "lefort=b.stl", "--out", "o"], ["b.stl"]),
        Case(cmd, "--bone garbage file", [*base, "--bone", "lefort=b.stl", "--out", "o"], ["b.stl"],
             {"b.stl": "solid x\nnot a facet\n"}),
        Case(cmd, "--mesh without --plan", ["--mesh", "{F}/face.inp", "--no-preview", "--out", "o"], ["--plan"]),
    ]

    # static database
    cmd = "static database"
    base = ["--resolution", "coarse", "--workers", "0"]
    cases += [
        Case(cmd, "--plans 0", [*base, "--plans", "0", "--out", "d.h5"], ["--plans"]),
        Case(cmd, "--plans -3", [*base, "--plans", "-3", "--out", "d.h5"], ["--plans", "-3"]),
        Case(cmd, "--subjects 0", [*base, "--subjects", "0", "--plans", "2", "--out", "d.h5"], ["--subjects"]),
        Case(cmd, "--workers -1", ["--resolution", "coarse", "--workers", "-1", "--plans", "2", "--out", "d.h5"],
             ["--workers"]),
        Case(cmd, "--poisson-range reversed", [*base, "--plans", "2", "--poisson-range", "0.49", "0.3",
                                               "--out", "d.h5"], ["--poisson-range", "0.49"]),
        Case(cmd, "--poisson-range 0.6", [*base, "--plans", "2", "--poisson-range", "0.3", "0.6",
                                          "--out", "d.h5"], ["--poisson-range", "0.6"]),
        Case(cmd, "--out a folder", [*base, "--plans", "2", "--out", "folder"], ["folder"], {"folder/x": "x"}),
        Case(cmd, "--out under a missing folder", [*base, "--plans", "2", "--out", "nowhere/d.h5"], ["nowhere"]),
        Case(cmd, "--out an impact database", [*base, "--plans", "2", "--out", "impact.h5"], ["impact.h5"],
             copy=["impact.h5"]),
        Case(cmd, "rerun with another --sliding", [*base, "--plans", "3", "--sliding", "none", "--out", "static.h5"],
             ["--sliding", "sliding"], copy=["static.h5"]),
        Case(cmd, "--out a garbage .h5", [*base, "--plans", "2", "--out", "junk.h5"], ["junk.h5"],
             {"junk.h5": binary}),
    ]

    # static train
    cmd = "static train"
    cases += [
        Case(cmd, "missing database", ["--data", "nothere.h5", "--out", "m"], ["nothere.h5"]),
        Case(cmd, "impact database", ["--data", "{F}/impact.h5", "--out", "m"], ["impact.h5"]),
        Case(cmd, "garbage database", ["--data", "junk.h5", "--out", "m"], ["junk.h5"], {"junk.h5": binary}),
        Case(cmd, "empty database", ["--data", "empty.h5", "--out", "m"], ["empty.h5"], {"empty.h5": ""}),
        Case(cmd, "--epochs 0", ["--data", "{F}/static.h5", "--epochs", "0", "--out", "m"], ["--epochs"]),
        Case(cmd, "--batch-size -1", ["--data", "{F}/static.h5", "--batch-size", "-1", "--out", "m"],
             ["--batch-size"]),
        Case(cmd, "--lr 0", ["--data", "{F}/static.h5", "--lr", "0", "--out", "m"], ["--lr"]),
        Case(cmd, "--test-subjects absent", ["--data", "{F}/static.h5", "--test-subjects", "7", "--epochs", "1",
                                              "--network", "tiny", "--out", "m"], ["7", "--test-subjects"]),
        Case(cmd, "--out an existing file", ["--data", "{F}/static.h5", "--epochs", "1", "--network", "tiny",
                                             "--out", "taken"], ["taken"], dict(out_files)),
        Case(cmd, "--out under /proc", ["--data", "{F}/static.h5", "--epochs", "1", "--network", "tiny",
                                        "--out", "/proc/x"], ["/proc/x"]),
        Case(cmd, "--device cuda without GPU", ["--data", "{F}/static.h5", "--epochs", "1", "--network", "tiny",
                                                "--device", "cuda", "--out", "m"], ["cuda"]),
        Case(cmd, "--test-subjects every subject", ["--data", "{F}/static.h5", "--test-subjects", "0", "--epochs",
                                                    "1", "--network", "tiny", "--out", "m"], ["--test-subjects"]),
        Case(cmd, "--material-channels, one Poisson's ratio", ["--data", "{F}/static.h5", "--material-channels",
                                                               "--epochs", "1", "--network", "tiny", "--out", "m"],
             ["material", "--poisson-range"]),
    ]

    # static evaluate
    cmd = "static evaluate"
    cases += [
        Case(cmd, "missing model", ["--model", "nomodel", "--data", "{F}/static.h5", "--out", "e"], ["nomodel"]),
        Case(cmd, "impact model", ["--model", "{F}/imodel", "--data", "{F}/static.h5", "--out", "e"], ["imodel"]),
        Case(cmd, "impact database", ["--model", "{F}/smodel", "--data", "{F}/impact.h5", "--out", "e"],
             ["impact.h5"]),
        Case(cmd, "database of another sliding model", ["--model", "{F}/smodel", "--data", "{F}/static_none.h5",
                                                         "--out", "e"], ["sliding", "--sliding"]),
        Case(cmd, "missing database", ["--model", "{F}/smodel", "--data", "nothere.h5", "--out", "e"],
             ["nothere.h5"]),
        Case(cmd, "empty model folder", ["--model", "emptymodel", "--data", "{F}/static.h5", "--out", "e"],
             ["emptymodel"], {"emptymodel/.keep": ""}),
        Case(cmd, "--out an existing file", ["--model", "{F}/smodel", "--data", "{F}/static.h5", "--no-preview",
                                             "--out", "taken"], ["taken"], dict(out_files)),
    ]

    # static predict
    cmd = "static predict"
    cases += [
        Case(cmd, "impact model", ["--model", "{F}/imodel", "--out", "p"], ["imodel"]),
        Case(cmd, "missing model", ["--model", "nomodel", "--out", "p"], ["nomodel"]),
        Case(cmd, "plan key typo", ["--model", "{F}/smodel", "--plan", "typo.toml", "--no-preview", "--out", "p"],
             ["translaton_mm"], dict(plans)),
        Case(cmd, "plan out of range without --force", ["--model", "{F}/smodel", "--plan", "large.toml",
                                                        "--no-preview", "--out", "p"], ["--force"], dict(plans)),
        Case(cmd, "metres mesh", ["--model", "{F}/smodel", "--mesh", "metres.inp", "--plan", "plan.toml",
                                  "--no-preview", "--out", "p"], ["metres.inp", "--units"], dict(mesh_files)),
        Case(cmd, "another resolution", ["--model", "{F}/smodel", "--resolution", "paper", "--no-preview",
                                         "--out", "p"], ["paper", "--resolution"]),
        Case(cmd, "--out under /proc", ["--model", "{F}/smodel", "--no-preview", "--out", "/proc/x"], ["/proc/x"]),
    ]

    # impact simulate
    cmd = "impact simulate"
    scenes = {
        "typo.toml": "[ball]\nvelocty = 30.0\n",
        "type.toml": "[ball]\nvelocity = \"fast\"\n",
        "syntax.toml": "[ball\nvelocity = 30.0\n",
        "section.toml": "[bal]\nvelocity = 30.0\n",
        "radius.toml": "[ball]\nradius = -5.0\n",
        "skull.toml": _skull_scene(),
        "scene.json": "{}",
    }
    cases += [
        Case(cmd, "scene key typo", ["--scene", "typo.toml", *IMPACT, "--out", "o"], ["velocty"], dict(scenes)),
        Case(cmd, "scene wrong type", ["--scene", "type.toml", *IMPACT, "--out", "o"], ["velocity", "fast"],
             dict(scenes)),
        Case(cmd, "scene TOML syntax", ["--scene", "syntax.toml", *IMPACT, "--out", "o"], ["syntax.toml"],
             dict(scenes)),
        Case(cmd, "scene unknown section", ["--scene", "section.toml", *IMPACT, "--out", "o"], ["bal"],
             dict(scenes)),
        Case(cmd, "scene negative radius", ["--scene", "radius.toml", *IMPACT, "--out", "o"], ["radius"],
             dict(scenes)),
        Case(cmd, "scene not TOML", ["--scene", "scene.json", *IMPACT, "--out", "o"], ["scene.json"], dict(scenes)),
        Case(cmd, "missing scene", ["--scene", "nothere.toml", *IMPACT, "--out", "o"], ["nothere.toml"]),
        Case(cmd, "ball through the skull", ["--scene", "skull.toml", "--out", "o"], ["--duration"], dict(scenes)),
        Case(cmd, "--velocity 0", [*IMPACT, "--velocity", "0", "--out", "o"], ["--velocity", "0"]),
        Case(cmd, "--velocity -30", [*IMPACT, "--velocity", "-30", "--out", "o"], ["--velocity", "-30"]),
        Case(cmd, "--velocity nan", [*IMPACT, "--velocity", "nan", "--out", "o"], ["--velocity", "nan"]),
        Case(cmd, "--duration 0", [*IMPACT, "--duration", "0", "--out", "o"], ["--duration"]),
        Case(cmd, "--mass-scaling 0", [*IMPACT, "--integrator", "explicit", "--mass-scaling", "0", "--out", "o"],
             ["--mass-scaling"]),
        Case(cmd, "--safety 2", [*IMPACT, "--integrator", "explicit", "--safety", "2", "--out", "o"], ["--safety"]),
        Case(cmd, "--threads 0", [*IMPACT, "--threads", "0", "--out", "o"], ["--threads"]),
        Case(cmd, "--out an existing file", [*IMPACT, "--integrator", "quasi-static", "--out", "taken"], ["taken"],
             dict(out_files)),
        Case(cmd, "--out under /proc", [*IMPACT, "--integrator", "quasi-static", "--out", "/proc/x"], ["/proc/x"]),
    ]

    # impact database
    cmd = "impact database"
    base = [*IMPACT, *EXPLICIT, "--workers", "0"]
    cases += [
        Case(cmd, "empty velocity list", [*base, "--velocities", "", "--out", "d.h5"], ["--velocities"]),
        Case(cmd, "velocity list with a word", [*base, "--velocities", "30,fast", "--out", "d.h5"],
             ["fast", "--velocities"]),
        Case(cmd, "negative velocity", [*base, "--velocities", "30,-40", "--out", "d.h5"], ["-40", "--velocities"]),
        Case(cmd, "ball through the skull", [*base, "--velocities", "30,40", "--duration", "0.9", "--out", "d.h5"],
             ["--duration"]),
        Case(cmd, "--workers -1", [*IMPACT, "--workers", "-1", "--velocities", "30", "--out", "d.h5"],
             ["--workers"]),
        Case(cmd, "--out a static database", [*base, "--velocities", "30,40", "--out", "static.h5"], ["static.h5"],
             copy=["static.h5"]),
        Case(cmd, "rerun with another --order", [*IMPACT[:2], "--order", "2", "--ball", "rigid", *EXPLICIT,
                                                 "--workers", "0", "--velocities", "30,40", "--held-out", "35",
                                                 "--out", "impact.h5"], ["order", "--order"], copy=["impact.h5"]),
        Case(cmd, "--out a garbage .h5", [*base, "--velocities", "30", "--out", "junk.h5"], ["junk.h5"],
             {"junk.h5": binary}),
        Case(cmd, "--out under a missing folder", [*base, "--velocities", "30", "--out", "nowhere/d.h5"],
             ["nowhere"]),
        Case(cmd, "scene key typo", [*base, "--scene", "typo.toml", "--velocities", "30", "--out", "d.h5"],
             ["velocty"], dict(scenes)),
    ]

    # impact train
    cmd = "impact train"
    cases += [
        Case(cmd, "static database", ["--data", "{F}/static.h5", "--epochs", "1", "--out", "m"], ["static.h5"]),
        Case(cmd, "missing database", ["--data", "nothere.h5", "--out", "m"], ["nothere.h5"]),
        Case(cmd, "garbage database", ["--data", "junk.h5", "--out", "m"], ["junk.h5"], {"junk.h5": binary}),
        Case(cmd, "--epochs -1", ["--data", "{F}/impact.h5", "--epochs", "-1", "--out", "m"], ["--epochs"]),
        Case(cmd, "--config typo", ["--data", "{F}/impact.h5", "--config", "sead", "--out", "m"],
             ["sead", "--config"]),
        Case(cmd, "--out an existing file", ["--data", "{F}/impact.h5", "--epochs", "1", "--out", "taken"],
             ["taken"], dict(out_files)),
        Case(cmd, "--out under /proc", ["--data", "{F}/impact.h5", "--epochs", "1", "--out", "/proc/x"],
             ["/proc/x"]),
        Case(cmd, "--max-minutes -1", ["--data", "{F}/impact.h5", "--max-minutes", "-1", "--out", "m"],
             ["--max-minutes"]),
        Case(cmd, "--device cuda without GPU", ["--data", "{F}/impact.h5", "--epochs", "1", "--device", "cuda",
                                                "--out", "m"], ["cuda", "--device"]),
        Case(cmd, "--split velocity without held-out velocities", ["--data", "{F}/impact_no_held.h5", "--split",
                                                                   "velocity", "--epochs", "1", "--out", "m"],
             ["held-out", "--split"]),
    ]

    # impact evaluate
    cmd = "impact evaluate"
    cases += [
        Case(cmd, "static model", ["--model", "{F}/smodel", "--data", "{F}/impact.h5", "--out", "e"], ["smodel"]),
        Case(cmd, "static database", ["--model", "{F}/imodel", "--data", "{F}/static.h5", "--out", "e"],
             ["static.h5"]),
        Case(cmd, "missing model", ["--model", "nomodel", "--data", "{F}/impact.h5", "--out", "e"], ["nomodel"]),
        Case(cmd, "--nodes out of range", ["--model", "{F}/imodel", "--data", "{F}/impact.h5", "--nodes",
                                           "999999", "--out", "e"], ["999999", "--nodes"]),
        Case(cmd, "--frames a word", ["--model", "{F}/imodel", "--data", "{F}/impact.h5", "--frames", "x",
                                      "--out", "e"], ["--frames"]),
        Case(cmd, "--frames out of range", ["--model", "{F}/imodel", "--data", "{F}/impact.h5", "--frames", "99",
                                            "--out", "e"], ["99", "--frames"]),
        Case(cmd, "--nodes empty", ["--model", "{F}/imodel", "--data", "{F}/impact.h5", "--nodes", ",",
                                    "--out", "e"], ["--nodes", "nodes"]),
        Case(cmd, "--nodes not a test node", ["--model", "{F}/imodel", "--data", "{F}/impact.h5", "--nodes", "0",
                                              "--out", "e"], ["--nodes"]),
        Case(cmd, "--out an existing file", ["--model", "{F}/imodel", "--data", "{F}/impact.h5", "--out", "taken"],
             ["taken"], dict(out_files)),
    ]

    # impact predict
    cmd = "impact predict"
    cases += [
        Case(cmd, "static model", ["--model", "{F}/smodel", "--velocity", "30", "--out", "p"], ["smodel"]),
        Case(cmd, "missing model", ["--model", "nomodel", "--velocity", "30", "--out", "p"], ["nomodel"]),
        Case(cmd, "--velocity -30", ["--model", "{F}/imodel", "--velocity", "-30", "--out", "p"],
             ["--velocity", "-30"]),
        Case(cmd, "--velocity nan", ["--model", "{F}/imodel", "--velocity", "nan", "--out", "p"],
             ["--velocity", "nan"]),
        Case(cmd, "--out under /proc", ["--model", "{F}/imodel", "--velocity", "30", "--out", "/proc/x"],
             ["/proc/x"]),
    ]

    # phantom
    cmd = "phantom"
    cases += [
        Case(cmd, "unknown phantom", ["face-hex8", "--out", "f.inp"], ["face-hex8"]),
        Case(cmd, "unknown suffix", ["face-hex", "--resolution", "coarse", "--out", "f.xyz"], ["f.xyz"]),
        Case(cmd, "--mouth-open -5", ["face-hex", "--resolution", "coarse", "--mouth-open", "-5", "--out", "f.inp"],
             ["--mouth-open", "-5"]),
        Case(cmd, "--out under /proc", ["face-hex", "--resolution", "coarse", "--out", "/proc/x.inp"], ["/proc/x"]),
        Case(cmd, "--out an existing folder", ["face-hex", "--resolution", "coarse", "--out", "folder"],
             ["folder"], {"folder/x": "x"}),
        Case(cmd, "--preview under /proc", ["face-hex", "--resolution", "coarse", "--out", "f.inp", "--preview",
                                            "/proc/x.png"], ["/proc/x"]),
    ]

    # demo
    cmd = "demo"
    cases += [
        Case(cmd, "--out an existing file", ["--resolution", "coarse", "--no-preview", "--out", "taken"], ["taken"],
             dict(out_files)),
        Case(cmd, "--out under /proc", ["--resolution", "coarse", "--no-preview", "--out", "/proc/x"], ["/proc/x"]),
        Case(cmd, "unknown resolution", ["--resolution", "corse", "--out", "d"], ["corse"]),
        Case(cmd, "--threads -2", ["--resolution", "coarse", "--no-preview", "--threads", "-2", "--out", "d"],
             ["--threads"]),
    ]
    return cases


# ----------------------------------------------------------------------------------------------
# running and judging


def _norm(text: str) -> str:
    return text.lower().replace("_", "-")


def judge(returncode: int, stderr: str, names: list[str]) -> tuple[str, bool, str]:
    """(the error line, whether it names the option as typed, why the row is not clear: '' when it is).

    A token ``--option`` also matches the option's word (``plans`` in ``plans = 0``); the second
    value says whether the line holds the option itself, in the command line's terms."""
    lines = [ln for ln in stderr.splitlines() if "error:" in ln]
    line = lines[-1].strip() if lines else ""
    words = {_norm(t) for t in names} | {_norm(t).lstrip("-") for t in names if t.startswith("--")}
    named = any(w in _norm(line) for w in words)
    as_option = any(t.startswith("--") and t in line for t in names)
    reasons = []
    if returncode != 2:
        reasons.append(f"exit {returncode}")
    if "Traceback" in stderr:
        reasons.append("traceback")
    if len(lines) != 1:
        reasons.append(f"{len(lines)} error lines")
    if lines and not named:
        reasons.append("does not name " + " or ".join(names))
    return line, as_option, "; ".join(reasons)


def run_case(case: Case) -> dict:
    with tempfile.TemporaryDirectory(prefix="bad_input_") as tmp:
        cwd = Path(tmp)
        for name, content in case.files.items():
            path = cwd / name
            path.parent.mkdir(parents=True, exist_ok=True)
            (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
        for name in case.copy:
            shutil.copy(FIXTURES / name, cwd / name)
        before = {p.relative_to(cwd) for p in cwd.rglob("*")}
        args = [a.replace("{F}", str(FIXTURES)) for a in case.args]
        proc, seconds = toolkit(*case.command.split(), *args, cwd=cwd)
        wrote = sorted(str(p.relative_to(cwd)) for p in cwd.rglob("*") if p.relative_to(cwd) not in before)
    line, as_option, why = judge(proc.returncode, proc.stderr, case.names)
    options = [t for t in case.names if t.startswith("--")]
    if not line:
        tail = [ln for ln in (proc.stderr or proc.stdout).strip().splitlines() if ln.strip()]
        line = tail[-1].strip() if tail else ""
    return {"command": case.command, "case": case.case, "exit_code": proc.returncode, "error": line[:300],
            "clear": not why, "not_clear_because": why,
            "names_option": as_option if options else None, "traceback": "Traceback" in proc.stderr,
            "seconds": round(seconds, 2), "left_files": bool(wrote), "wrote": " ".join(wrote)[:200],
            "args": " ".join(case.args)}


# ----------------------------------------------------------------------------------------------
# interrupts

#: the long commands, run tiny; "{F}" is the fixtures folder. Ctrl-C reaches the whole process
#: group (the command and its worker processes), as in a terminal.
LONG = {
    "static database": ["static", "database", "--resolution", "coarse", "--plans", "24", "--out", "db.h5"],
    "impact database": ["impact", "database", *IMPACT, *EXPLICIT,
                       "--velocities", ",".join(str(v) for v in range(20, 51, 2)), "--out", "db.h5"],
    "static train": ["static", "train", "--data", "{F}/static.h5", "--network", "tiny", "--epochs", "400",
                     "--out", "m"],
    "impact train": ["impact", "train", "--data", "{F}/impact.h5", "--epochs", "300", "--out", "m"],
}


def finished(command: str, cwd: Path) -> tuple[int, int | None]:
    """(finished simulations or epochs on disk, the planned count when the file records it)."""
    if command.endswith("database"):
        from toolkit.common.training.database import database_status

        db = cwd / "db.h5"
        if not db.exists():
            return 0, None
        try:
            status = database_status(db)
        except Exception:  # a file without the database's layout yet: nothing finished
            return 0, None
        return status.records + status.pending, status.planned
    import torch

    checkpoint = cwd / "m" / "checkpoint.pt"
    if not checkpoint.exists():
        return 0, None
    return int(torch.load(checkpoint, map_location="cpu", weights_only=False)["epoch"]), None


def start(args: list[str], cwd: Path) -> subprocess.Popen:
    """The command in a process group of its own, with Ctrl-C's default action: a benchmark started
    in the background of a shell ignores SIGINT, and its commands would inherit that."""
    return subprocess.Popen([PY, "-m", "toolkit", *[a.replace("{F}", str(FIXTURES)) for a in args]], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=_default_sigint)


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _noise(stderr: str) -> str:
    """The first line of stderr that is neither a progress bar nor the command's own message: a
    warning or a traceback printed on the way out ('' when there is none)."""
    for line in stderr.splitlines():
        text = line.strip()
        if any(word in text for word in ("Traceback", "Warning", "warn(", "leaked")):
            return text
    return ""


def interrupt_rows(command: str, fractions=(0.3, 0.6, 0.9), early: float = 0.5) -> list[dict]:
    """One uninterrupted run (the full count and its time T), then a fresh run per interrupt time
    (``early`` s, and each fraction of T): Ctrl-C at that time, count, rerun the same command
    (``--resume`` added for a training, as its refusal says), count again."""
    args = LONG[command]
    rows = []
    with tempfile.TemporaryDirectory(prefix="interrupt_") as tmp:
        t0 = time.perf_counter()
        proc = start(args, Path(tmp))
        _, err = proc.communicate()
        total_s = time.perf_counter() - t0
        full, planned = finished(command, Path(tmp))
        if proc.returncode != 0:
            raise RuntimeError(f"{command}: {err[-2000:]}")
    for at in (early, *(f * total_s for f in fractions)):
        with tempfile.TemporaryDirectory(prefix="interrupt_") as tmp:
            cwd = Path(tmp)
            proc = start(args, cwd)
            time.sleep(at)
            running = proc.poll() is None
            if running:
                os.killpg(proc.pid, signal.SIGINT)
            _, err = proc.communicate()
            before, _ = finished(command, cwd)
            lines = [ln.strip() for ln in err.splitlines() if ln.strip()]
            said = [ln for ln in lines if "interrupted" in ln.lower()]
            rerun_args = [*args, "--resume"] if command.endswith("train") and (cwd / "m").exists() else args
            t1 = time.perf_counter()
            again = start(rerun_args, cwd)
            _, err2 = again.communicate()
            rerun_s = time.perf_counter() - t1
            after, _ = finished(command, cwd)
            lines2 = [ln.strip() for ln in err2.splitlines() if ln.strip()]
            rows.append({"command": command, "interrupt_s": round(at, 2), "full_run_s": round(total_s, 1),
                         "interrupted": running, "exit_code": proc.returncode,
                         "message": (said or lines or [""])[-1][:300], "traceback": "Traceback" in err,
                         "other_output": _noise(err)[:300], "done_before": before,
                         "done_after_rerun": after, "full": full, "planned": planned,
                         "nothing_lost": after >= before, "rerun_exit_code": again.returncode,
                         "rerun_completes": again.returncode == 0 and after == full,
                         "rerun_s": round(rerun_s, 1),
                         "rerun_message": (lines2[-1] if again.returncode and lines2 else "")[:300],
                         "rerun": " ".join(rerun_args[len(command.split()):])})
            print(rows[-1], flush=True)
    return rows


#: the short commands (seconds to a minute), whose output folder must hold nothing or a result
#: marked as unfinished after a Ctrl-C; "{F}" is the fixtures folder
SHORT = {
    "static simulate": ["static", "simulate", "--resolution", "paper", "--no-preview", "--out", "o"],
    "impact simulate": ["impact", "simulate", *IMPACT, *EXPLICIT, "--no-preview", "--out", "o"],
    "static predict": ["static", "predict", "--model", "{F}/smodel", "--no-preview", "--out", "o"],
    "static evaluate": ["static", "evaluate", "--model", "{F}/smodel", "--data", "{F}/static.h5", "--out", "o"],
    "impact predict": ["impact", "predict", "--model", "{F}/imodel", "--velocity", "35", "--out", "o"],
    "impact evaluate": ["impact", "evaluate", "--model", "{F}/imodel", "--data", "{F}/impact.h5", "--out", "o"],
}


def output_state(out: Path) -> str:
    """What an output folder holds: ``nothing``, ``complete`` (``summary.json`` with status
    finished, or ``metrics.json``), ``marked STATUS`` (``summary.json`` saying the run did not
    finish) or ``partial: FILES`` (files without either)."""
    import json

    files = sorted(p.name for p in out.iterdir()) if out.is_dir() else []
    if not files:
        return "nothing"
    if (out / "summary.json").is_file():
        status = json.loads((out / "summary.json").read_text()).get("status", "finished")
        return "complete" if status == "finished" else f"marked {status}"
    if (out / "metrics.json").is_file():
        return "complete"
    return "partial: " + " ".join(files)


def short_rows(command: str, fractions=(0.3, 0.6, 0.9), early: float = 0.5) -> list[dict]:
    """As :func:`interrupt_rows` for a short command: one uninterrupted run (its time T), then a
    fresh run per interrupt time with Ctrl-C, what the output folder holds, and the same
    command rerun into it."""
    args = SHORT[command]
    rows = []
    with tempfile.TemporaryDirectory(prefix="interrupt_") as tmp:
        t0 = time.perf_counter()
        proc = start(args, Path(tmp))
        _, err = proc.communicate()
        total_s = time.perf_counter() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"{command}: {err[-2000:]}")
    for at in (early, *(f * total_s for f in fractions)):
        with tempfile.TemporaryDirectory(prefix="interrupt_") as tmp:
            cwd = Path(tmp)
            proc = start(args, cwd)
            time.sleep(at)
            running = proc.poll() is None
            if running:
                os.killpg(proc.pid, signal.SIGINT)
            _, err = proc.communicate()
            state = output_state(cwd / "o")
            lines = [ln.strip() for ln in err.splitlines() if ln.strip()]
            said = [ln for ln in lines if "interrupted" in ln.lower()]
            again = start(args, cwd)
            _, err2 = again.communicate()
            after = output_state(cwd / "o")
            rows.append({"command": command, "interrupt_s": round(at, 2), "full_run_s": round(total_s, 1),
                         "interrupted": running, "exit_code": proc.returncode,
                         "message": (said or lines or [""])[-1][:300], "traceback": "Traceback" in err,
                         "other_output": _noise(err)[:300], "output": state[:200],
                         "output_ok": state in ("nothing", "complete") or state.startswith("marked"),
                         "rerun_exit_code": again.returncode, "rerun_output": after[:200],
                         "rerun_completes": again.returncode == 0 and after == "complete"})
            print(rows[-1], flush=True)
    return rows


def import_seconds(command: str) -> float:
    words = command.split()
    mods = MODULES[words[-1]].format(workflow=words[0])
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        subprocess.run([PY, "-c", f"import {mods}"], check=True)
        times.append(time.perf_counter() - t0)
    return min(times)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", default="", help="run only the commands whose name starts with this")
    ap.add_argument("--out", type=Path, default=RESULTS / "bad_inputs.csv")
    ap.add_argument("--interrupts", action="store_true",
                    help="instead, interrupt each long and short command at several times and rerun it "
                         "(writes bad_inputs_interrupts.csv and bad_inputs_interrupts_short.csv beside --out)")
    args = ap.parse_args(argv)
    build_fixtures()
    if args.interrupts:
        rows = [r for command in LONG if command.startswith(args.only) for r in interrupt_rows(command)]
        if rows:
            df = pd.DataFrame(rows)
            write_result(args.out.with_name(args.out.stem + "_interrupts.csv"), df)
            print(df.drop(columns=["message", "rerun_message", "rerun"]).to_string())
        rows = [r for command in SHORT if command.startswith(args.only) for r in short_rows(command)]
        if rows:
            df = pd.DataFrame(rows)
            write_result(args.out.with_name(args.out.stem + "_interrupts_short.csv"), df)
            print(df.drop(columns=["message"]).to_string())
        return 0
    cases = [c for c in catalogue() if c.command.startswith(args.only)]
    baseline = {c: import_seconds(c) for c in dict.fromkeys(c.command for c in cases)}
    rows = []
    for case in cases:
        row = run_case(case)
        row["import_s"] = round(baseline[case.command], 2)
        row["slow"] = row["seconds"] > 3 * row["import_s"]
        rows.append(row)
        flag = "clear" if row["clear"] else f"NOT CLEAR ({row['not_clear_because']})"
        print(f"{row['command']:16s} {row['case']:40s} {row['exit_code']:4d} {row['seconds']:6.2f} s  {flag}\n"
              f"    {row['error']}", flush=True)
    df = pd.DataFrame(rows)
    write_result(args.out, df, extra={"import_s": {k: round(v, 2) for k, v in baseline.items()},
                                      "slow_factor": 3})
    summary = df.groupby("command", sort=False).agg(cases=("case", "size"), clear=("clear", "sum"),
                                                    median_s=("seconds", statistics.median),
                                                    max_s=("seconds", "max"), slow=("slow", "sum"))
    print(summary.to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
