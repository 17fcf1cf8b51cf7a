"""The command line as a user meets it: version, help, option spellings, messages."""
import argparse
import json

import pytest
from tqdm import tqdm

from harness import cli
from harness.cli import build_parser, main
from harness.core.kitti import write_image_set


def test_version(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0 and capsys.readouterr().out.startswith("sotif-bench ")


def _options(parser: argparse.ArgumentParser):
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from ((f"{name} {opt}", help_) for opt, help_ in _options(sub))
        elif not isinstance(action, (argparse._HelpAction, argparse._VersionAction)):
            yield "/".join(action.option_strings) or action.dest, action.help


def test_every_option_has_a_help_text():
    options = list(_options(build_parser()))
    assert len(options) > 40 and [opt for opt, help_ in options if not help_] == []


@pytest.mark.parametrize("argv", [["run", "--models", ""], ["run", "--models", " , "],
                                  ["simulate", "--preset", "sotif", "--out", "x", "--weathers", ""]])
def test_an_empty_list_is_an_error(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    assert "is empty" in capsys.readouterr().err and list(tmp_path.iterdir()) == []


def test_split_is_a_name_or_a_file_in_predict_and_evaluate(make_onnx, tmp_path, dataset):
    onnx_path = make_onnx(tmp_path / "mine.onnx")
    write_image_set(tmp_path / "two.txt", ["000001", "000003"])
    write_image_set(dataset / "ImageSets" / "val.txt", ["000002"])
    pred = tmp_path / "pred"
    for split, frames in (("test", 6), (str(tmp_path / "two.txt"), 2)):
        assert main(["--quiet", "predict", "--onnx", str(onnx_path), "--data", str(dataset), "--split", split,
                     "--out", str(pred / split.replace("/", "_"))]) == 0
        assert len(list((pred / split.replace("/", "_")).glob("*.txt"))) == frames
    every = str(pred / "test")
    for labels in (dataset, dataset / "training" / "label_2"):
        for split, frames in (("val", 1), (str(tmp_path / "two.txt"), 2), (str(dataset / "ImageSets" / "test.txt"), 6)):
            out = tmp_path / "results.json"
            assert main(["--quiet", "evaluate", "--labels", str(labels), "--predictions", every, "--split", split,
                         "--output", str(out)]) == 0
            assert json.loads(out.read_text())["n_frames"] == frames
    # with --onnx, --split names the frames to predict and evaluate; --data-split is its former spelling
    for flag in ("--split", "--data-split"):
        out = tmp_path / flag / "results.json"
        assert main(["--quiet", "evaluate", "--onnx", str(onnx_path), "--data", str(dataset), flag, "val",
                     "--output", str(out)]) == 0
        assert json.loads(out.read_text())["n_frames"] == 1
    out = tmp_path / "both" / "results.json"
    assert main(["--quiet", "evaluate", "--onnx", str(onnx_path), "--data", str(dataset), "--split", "test",
                 "--data-split", "val", "--output", str(out)]) == 2
    assert not out.parent.exists()


def test_an_unknown_split_names_both_readings(make_onnx, tmp_path, dataset, capsys):
    onnx_path = make_onnx(tmp_path / "mine.onnx")
    assert main(["--quiet", "predict", "--onnx", str(onnx_path), "--data", str(dataset), "--split", "tset",
                 "--out", str(tmp_path / "p")]) == 2
    err = capsys.readouterr().err
    assert "--split tset: neither a split of" in err and "ImageSets/tset.txt" in err and "nor an ImageSets file" in err
    missing = tmp_path / "lists" / "mine.txt"
    assert main(["--quiet", "predict", "--onnx", str(onnx_path), "--data", str(dataset), "--split", str(missing),
                 "--out", str(tmp_path / "p")]) == 2
    assert f"--split {missing}: file not found" in capsys.readouterr().err
    out = tmp_path / "by_file_name"  # the split's file name, as ImageSets holds it
    assert main(["--quiet", "predict", "--onnx", str(onnx_path), "--data", str(dataset), "--split", "test.txt",
                 "--out", str(out)]) == 0
    assert sorted(p.stem for p in out.glob("*.txt")) == (dataset / "ImageSets" / "test.txt").read_text().split()


def test_an_error_lands_on_its_own_line_after_an_open_progress_bar(monkeypatch, capsys):
    def fails(a):
        bar = tqdm(total=10, desc="predict", file=__import__("sys").stderr)
        bar.update(3)
        raise ValueError("frame 000003: broken")
    monkeypatch.setattr(cli, "cmd_report", fails)
    assert main(["report", "somewhere"]) == 2
    err = capsys.readouterr().err
    assert err.endswith("\nsotif-bench report: error: frame 000003: broken\n")
    assert "predict" in err and not tqdm._instances


def _usage_error(argv, capsys) -> str:
    """The message of an argument argparse refuses (exit 2)."""
    with pytest.raises(SystemExit) as stop:
        main(argv)
    assert stop.value.code == 2
    return capsys.readouterr().err


OUTPUTS = [["simulate", "--preset", "train", "--out"], ["train", "--model", "pointpillars", "--data", "d", "--out"],
           ["export", "--model", "second", "--checkpoint", "c.pt", "--out"],
           ["predict", "--onnx", "m.onnx", "--data", "d", "--out"], ["evaluate", "--output"], ["run", "--out"],
           ["report", "r", "--sample"]]


@pytest.mark.parametrize("argv", OUTPUTS, ids=lambda argv: argv[0])
def test_an_empty_output_path_is_an_error(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # an empty path would be this folder
    assert f"argument {argv[-1]}: expected a path, got an empty string" in _usage_error(argv + [""], capsys)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("argv", [a for a in OUTPUTS if a[0] in ("simulate", "train", "predict", "run")],
                         ids=lambda argv: argv[0])
def test_an_output_folder_that_is_a_file_is_an_error(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "notes.txt").write_text("mine")
    assert "argument --out: notes.txt: is a file, expected a folder" in _usage_error(argv + ["notes.txt"], capsys)
    assert "notes.txt: is a file, so the folder notes.txt/sub cannot be made" in \
        _usage_error(argv + ["notes.txt/sub"], capsys)
    assert (tmp_path / "notes.txt").read_text() == "mine" and len(list(tmp_path.iterdir())) == 1


@pytest.mark.parametrize("argv", [OUTPUTS[0] + ["o"], OUTPUTS[1] + ["o"], ["evaluate", "--output", "r.json"]],
                         ids=lambda argv: argv[0])
def test_a_negative_seed_names_the_option(argv, capsys):
    assert "argument --seed: expected a non-negative integer, got '-3'" in _usage_error(argv + ["--seed", "-3"], capsys)


def test_simulate_into_a_folder_of_other_files_needs_force(tmp_path, monkeypatch, capsys):
    import simulator
    (tmp_path / "notes.txt").write_text("mine")
    argv = ["--quiet", "simulate", "--preset", "train", "--frames", "1", "--out", str(tmp_path)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"{tmp_path}: is not empty and holds no data set of this configuration (it has notes.txt)" in err
    assert "--force" in err and [p.name for p in tmp_path.iterdir()] == ["notes.txt"]
    calls = []
    monkeypatch.setattr(simulator, "generate", lambda out, **k: calls.append(k) or out)
    assert main(argv + ["--force"]) == 0 and calls[0]["force"] is True


def _help(argv, capsys) -> str:
    with pytest.raises(SystemExit) as stop:
        main([*argv, "--help"])
    assert stop.value.code == 0
    return capsys.readouterr().out


def test_every_command_says_what_it_does_with_an_example_and_the_valid_names(capsys):
    from models.zoo import MODEL_NAMES
    from simulator.weather import WEATHER_PRESETS
    commands = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction)).choices
    assert set(commands) == {"simulate", "train", "export", "predict", "evaluate", "run", "report", "import", "verdict"}
    for name in commands:
        text = _help([name], capsys)
        usage, description = text.split("\n\n")[:2]
        assert usage.startswith(f"usage: sotif-bench {name}") and len(description.split()) >= 15, name
        example = text.split("example")[-1]
        assert f"  sotif-bench {name} " in example and example.startswith(("s:\n", ":\n")), name
        assert max(map(len, text.splitlines())) <= 100, name
    flat = lambda text: " ".join(text.split())
    for name in ("train", "export", "run"):
        assert "Models: " + ", ".join(MODEL_NAMES) + "." in flat(_help([name], capsys))
    assert ", ".join(WEATHER_PRESETS) in flat(_help(["simulate"], capsys))


def test_weather_names_match_in_any_case_and_an_unknown_one_gets_a_suggestion(tmp_path, monkeypatch, capsys):
    import simulator
    calls = []
    monkeypatch.setattr(simulator, "generate", lambda out, **k: calls.append(k) or out)
    argv = ["--quiet", "simulate", "--preset", "sotif", "--frames", "2", "--out", str(tmp_path / "d")]
    assert main(argv + ["--weathers", "clearnoon, HARDRAINNIGHT,WetNoon"]) == 0
    assert calls[0]["weathers"] == ["ClearNoon", "HardRainNight", "WetNoon"]
    assert main(argv + ["--weathers", "ClearNoon,HardRainNite"]) == 2
    err = capsys.readouterr().err
    assert "--weathers: unknown weather preset 'HardRainNite' (did you mean HardRainNight or " in err
    assert "valid: ClearNoon, CloudyNoon" in err and len(calls) == 1
    assert main(argv + ["--weathers", "Sunny"]) == 2
    assert "unknown weather preset 'Sunny'; valid: ClearNoon" in capsys.readouterr().err


def test_model_names_match_in_any_case_and_an_unknown_one_gets_a_suggestion(tmp_path, monkeypatch, capsys):
    import harness.train
    calls = []
    monkeypatch.setattr(harness.train, "train", lambda model, *a, **k: calls.append(model.model) or tmp_path / "c.pt")
    argv = ["--quiet", "train", "--data", str(tmp_path), "--out", str(tmp_path / "o"), "--workers", "1", "--model"]
    assert main(argv + ["PointPillars"]) == 0 and calls == ["pointpillars"]
    assert main(argv + ["pointpilars"]) == 2
    assert "--model: unknown model 'pointpilars' (did you mean pointpillars?); valid: pointpillars, second" in \
        capsys.readouterr().err
    assert main(["--quiet", "run", "--models", "second,pvrcnn", "--out", str(tmp_path / "r")]) == 2
    assert "--models: unknown model 'pvrcnn' (did you mean pv_rcnn" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_resolve_names_against_plain_lookups():
    import difflib
    from harness.names import resolve_names
    valid = ["ClearNoon", "WetNoon", "HardRainNight"]
    assert resolve_names(["wetnoon", "CLEARNOON", "HardRainNight"], valid, "--x", "y") == ["WetNoon", "ClearNoon",
                                                                                          "HardRainNight"]
    for typo in ("ClearNon", "wetnon", "HardRain", "zzz"):
        with pytest.raises(ValueError) as e:
            resolve_names(["ClearNoon", typo], valid, "--x", "thing")
        close = difflib.get_close_matches(typo.lower(), [v.lower() for v in valid], n=3, cutoff=0.6)
        assert f"--x: unknown thing {typo!r}" in str(e.value) and ("did you mean" in str(e.value)) == bool(close)


def test_a_first_compile_prints_one_notice_and_a_cached_one_none(tmp_path):
    import os
    import subprocess
    import sys
    from harness.compile_notice import NOTICE
    (tmp_path / "kern.py").write_text("import numba\n\n\n@numba.njit(cache=True)\ndef f(x):\n    return x + 1\n\n\n"
                                      "@numba.njit(cache=True)\ndef g(x):\n    return f(x) * 2\n")
    code = ("from harness.compile_notice import announce_compiles; announce_compiles(); "
            "import kern; assert kern.g(1) == 4 and kern.f(2) == 3")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.getcwd()])}
    env.pop("NUMBA_CACHE_DIR", None)  # the cache beside kern.py
    runs = [subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300)
            for _ in range(2)]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr
    assert runs[0].stderr.count(NOTICE) == 1 and NOTICE not in runs[1].stderr


def test_simulate_bounds_makes_every_scenario_value_and_seed_probe(tmp_path, monkeypatch, capsys):
    import simulator
    from simulator.bounds import AXES, REFERENCES, Probe
    assert cli.BOUNDS_AXES == AXES  # spelled in the parser so that it imports no simulator
    assert all(name.split("_", 1)[0] in cli.BOUNDS_SCENARIOS for name in REFERENCES)
    calls = []
    monkeypatch.setattr(simulator, "generate", lambda out, **k: calls.append(k) or out)
    import simulator.dataset
    monkeypatch.setattr(simulator.dataset, "read_content_digest", lambda out: "x")
    base = ["--quiet", "simulate", "--preset", "bounds", "--out", str(tmp_path / "b")]
    assert main(base + ["--axis", "rain", "--values", "0,50", "--scenarios", "90-60_SEDAN_black,120-60_suv_silver",
                        "--noise-seeds", "0,2"]) == 0
    assert calls[0]["preset"] == "bounds" and calls[0]["instances"] == 1
    assert calls[0]["probes"] == tuple(Probe(s, "rain", v, k) for s in ("90-60_sedan_black", "120-60_suv_silver")
                                       for v in (0.0, 50.0) for k in (0, 2))
    assert main(base + ["--axis", "fog", "--values", "500"]) == 0  # every reference scenario, noise seed 0
    assert calls[1]["probes"] == tuple(Probe(s, "fog", 500.0, 0) for s in REFERENCES)
    assert main(["--quiet", "simulate", "--preset", "sweep", "--instances", "4", "--out", str(tmp_path / "s")]) == 0
    assert calls[2]["probes"] is None and calls[2]["instances"] == 4


@pytest.mark.parametrize("extra, message", [
    (["--preset", "bounds", "--axis", "rain"], "--preset bounds needs --values"),
    (["--preset", "bounds", "--values", "3"], "--preset bounds needs --axis"),
    (["--preset", "bounds", "--axis", "rain", "--values", "3,x"], "--values: 'x' is not a number"),
    (["--preset", "bounds", "--axis", "rain", "--values", "nan"], "--values: 'nan' is not a finite number"),
    (["--preset", "bounds", "--axis", "rain", "--values", "150"], "axis rain: value 150.0 outside 0.0-100.0 mm/h"),
    (["--preset", "bounds", "--axis", "water", "--values", "1", "--noise-seeds", "1.5"],
     "--noise-seeds: '1.5' is not an integer"),
    (["--preset", "bounds", "--axis", "water", "--values", "1", "--noise-seeds", "-1"], "noise seed must be an integer >= 0"),
    (["--preset", "bounds", "--axis", "water", "--values", "1", "--scenarios", "90-60_sedan_gold"],
     "unknown reference scenario '90-60_sedan_gold'"),
    (["--preset", "bounds", "--axis", "water", "--values", "1", "--instances", "2"],
     "a bounds set takes neither frames, weathers nor instances"),
    (["--preset", "sweep", "--values", "1"], "--values goes with --preset bounds only"),
    (["--preset", "sotif", "--axis", "fog"], "--axis goes with --preset bounds only"),
])
def test_simulate_bounds_refuses_bad_probes_by_name(extra, message, tmp_path, capsys):
    assert main(["--quiet", "simulate", "--out", str(tmp_path / "b"), *extra]) == 2
    assert message in capsys.readouterr().err and list(tmp_path.iterdir()) == []
