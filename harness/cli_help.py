"""What each ``sotif-bench`` subcommand's ``--help`` says above and below its options: what the
command does, the valid model and weather names, and an example.

The names come from their one place (``models.zoo.MODEL_NAMES``, ``simulator.weather.WEATHER_PRESETS``),
read only when a help is printed: those modules load torch and numba, which a command's start-up
should not pay for.
"""
from __future__ import annotations

import argparse
import textwrap

COMMANDS = {  # name: (what it does, examples)
    "simulate": ("Simulate the SOTIF cut-out scenario (--preset sotif: the test set, under every weather preset) "
                 "or randomised training scenes (--preset train) with a ray-cast LiDAR and camera, and write a KITTI "
                 "data set with meta/frames.csv. --preset sweep draws scenario instances under continuous weather; "
                 "--preset bounds holds reference scenarios fixed and varies one axis (a controlled sweep, one "
                 "instance per scenario, value and noise seed), the set `verdict` places a detector's boundary on. "
                 "A stopped simulate resumes. Weather presets (CARLA's names, any case): {weathers}.",
                 ["sotif-bench simulate --preset sotif --out data/sotif --frames 42 --weathers ClearNoon,HardRainNoon",
                  "sotif-bench simulate --preset train --out data/train --workers 2",
                  "sotif-bench simulate --preset bounds --axis rain --values 0,25,50,100 --scenarios "
                  "90-60_sedan_silver,90-60_sedan_black --noise-seeds 0,1 --out data/rain_bounds"]),
    "train": ("Train one detector on the train split of a KITTI data set (scored on val after every epoch) and "
              "write OUT/checkpoint.pt; a stopped training resumes. Models: {models}.",
              ["sotif-bench train --model pointpillars --data data/train --out runs/pointpillars",
               "sotif-bench train --model pv_rcnn --data data/train --out runs/pv_rcnn --init-from "
               "runs/second/checkpoint.pt"]),
    "export": ("Export a checkpoint written by train to one self-contained ONNX file that follows the contract "
               "(inputs points [N, 4]; outputs boxes, scores; see the README). Models: {models}.",
               ["sotif-bench export --model pointpillars --checkpoint runs/pointpillars/checkpoint.pt "
                "--out pointpillars.onnx"]),
    "import": ("Import a published checkpoint (OpenPCDet's PointPillars, SECOND, Part-A2 or PV-RCNN, "
               "MMDetection3D's DV-SECOND; KITTI 3-class) as our kitti-profile checkpoint, read without running code from it; every tensor is "
               "mapped or the file is refused, naming what is missing, extra or misshapen. Then export it as usual.",
               ["sotif-bench import --from openpcdet --model second --checkpoint second_7862.pth --out second.pt",
                "sotif-bench import --from mmdet3d --model dv_second --checkpoint dv_second_kitti.pth --out dv.pt"]),
    "predict": ("Run an ONNX detector (one of ours, or your own that follows the contract) on a split of a KITTI "
                "data set with onnxruntime or OpenVINO, and write one KITTI result file per frame plus "
                "predict.json (latency). A stopped predict resumes.",
                ["sotif-bench predict --onnx pointpillars.onnx --data data/sotif --split test --out pred/pointpillars"]),
    "evaluate": ("Score KITTI result files against labels: KITTI AP11/AP40 (2D, BEV, 3D, AOS; easy, moderate, "
                 "hard), the headline AP40 over all distances without the 2D-height filter, distance bins, recall "
                 "and, with --group-by, per-group tables with 95% intervals. Every AP is printed beside the cars "
                 "it counts, with the cap KITTI's sampling puts on it over few cars. With --onnx, predict first "
                 "(bring your own detector).",
                 ["sotif-bench evaluate --labels data/sotif --predictions pred/pointpillars --split test "
                  "--group-by weather --output results.json",
                  "sotif-bench evaluate --onnx my_detector.onnx --data data/sotif --output results.json"]),
    "run": ("The whole benchmark: simulate both data sets, train, export, predict and evaluate each model, and "
            "write the report (reports/NAME/index.html); a second run skips every stage whose inputs have not "
            "changed. Models: {models}.",
            ["sotif-bench run --profile quick --models pointpillars,second --out reports/quick",
             "sotif-bench run --out reports/default --jobs 2",
             "sotif-bench run --models none --checkpoints imported/ --lidar-model carla --instances 1 "
             "--out reports/published"]),
    "verdict": ("The SOTIF verdict of a detector's KITTI result files on a scenario set (simulate --instances N or "
                "--preset sweep): per instance whether a reference that confirms the slow vehicle as soon as it is "
                "perceivable could stop (preventable, or why not), when the detector confirms it (3 in-path hits "
                "within 0.5 s), its delay behind the reference, the deceleration its decision leaves (pass <= 6 "
                "m/s^2) and phantom in-path boxes per hour. FILE.csv gets the instance table, any other name the "
                "whole result as JSON.",
                ["sotif-bench verdict --data data/sweep --predictions pred/pointpillars --output verdict.json",
                 "sotif-bench verdict --data data/sweep --predictions pred/mine --latency-ms 120 --output mine.csv"]),
    "report": ("Render a run folder's tables, figures, report.md and index.html again from its result files; "
               "with --sample, publish them as the repository's sample (reports/sample); with --docs, write the "
               "README's results table and the numbers of docs/results.md from the sample's tables.",
               ["sotif-bench report reports/default", "sotif-bench report reports/default --sample reports/sample",
                "sotif-bench report --docs",
                "sotif-bench report reports/default --sample reports/sample --docs"]),
}


def names() -> dict[str, str]:
    """The valid model and weather names, comma-separated (imports torch and numba: help time only)."""
    from models.zoo import MODEL_NAMES
    from simulator.weather import WEATHER_PRESETS
    return {"models": ", ".join(MODEL_NAMES), "weathers": ", ".join(WEATHER_PRESETS)}


class CommandParser(argparse.ArgumentParser):
    """A subcommand's parser: its description names the valid models and weathers and is wrapped, and its
    examples are broken before an option, to the width of the terminal, when the help is printed."""

    def format_help(self) -> str:
        width = self._get_formatter()._width
        what, examples = COMMANDS[self.prog.split()[-1]]
        what = what.format(**names()) if "{" in what else what
        self.description = textwrap.fill(what, width)
        self.epilog = "example" + "s" * (len(examples) > 1) + ":\n" + "\n".join(_wrap(e, width) for e in examples)
        return super().format_help()


def _wrap(command: str, width: int) -> str:
    """A command line indented by 2, broken before its options into lines of about ``width``, continued by
    a backslash."""
    parts = command.split(" --")
    lines = [parts[0]]
    for part in parts[1:]:
        if len(lines[-1]) + len(part) + 5 > width - 2:
            lines.append("    --" + part)
        else:
            lines[-1] += " --" + part
    return "  " + " \\\n  ".join(lines)


def command_text(name: str) -> dict:
    """``add_parser`` keywords of subcommand ``name``: a description and examples, laid out by
    ``CommandParser`` when printed."""
    return {"description": COMMANDS[name][0], "formatter_class": argparse.RawDescriptionHelpFormatter}
