import json

import pytest

from gcs.commands import plan as plan_cmd
from gcs.planning.areas import SearchArea
from gcs.planning.camera import spacing_from_swath
from gcs.planning.division import DroneSpec, InsufficientCapabilityError
from gcs.planning.planner import PlanConfig, plan_search
from protocol.taskfile import load_task_text

U = [
    [47.0, 8.0],
    [47.0, 8.004],
    [47.003, 8.004],
    [47.003, 8.0027],
    [47.001, 8.0027],
    [47.001, 8.0013],
    [47.003, 8.0013],
    [47.003, 8.0],
]


def _main(argv):
    import argparse

    parser = argparse.ArgumentParser()
    sub = parser.add_subparsers(dest="command")
    plan_cmd.register(sub)
    args = parser.parse_args(argv)
    return args.run(args)


@pytest.mark.parametrize(
    "extra",
    [
        ["--drones", "3", "--swath", "30", "--alt", "40", "--battery", "1,0.6,0.3"],
        [
            "--drones",
            "2",
            "--division",
            "region",
            "--pattern",
            "spiral",
            "--camera",
            "res=640,fov=60,minpx=20",
        ],
        ["--drones", "2", "--pattern", "segmented", "--swath", "25", "--alt", "30", "--return", "land_home"],
    ],
)
def test_cli_writes_three_files(tmp_path, capsys, extra):
    area = tmp_path / "u.json"
    area.write_text(json.dumps(U))
    out = tmp_path / "out"
    rc = _main(["plan", str(area), "--home", "46.9995,8.0", "--out", str(out), *extra])
    assert rc == 0
    tf = load_task_text((out / "mission.json").read_text())
    assert len(tf.plans) == int(extra[1])
    gj = json.loads((out / "paths.geojson").read_text())
    assert sum(f["properties"]["role"] == "path" for f in gj["features"]) == int(extra[1])
    assert (out / "plan.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    summary = json.loads(capsys.readouterr().out)
    assert summary["coverage"]["covered_pct"] > 99.0


def test_cli_rejects_self_intersecting_area(tmp_path, capsys):
    area = tmp_path / "bow.json"
    area.write_text(json.dumps([[47.0, 8.0], [47.001, 8.001], [47.001, 8.0], [47.0, 8.001]]))
    rc = _main(["plan", str(area), "--swath", "20", "--alt", "30", "--out", str(tmp_path / "o")])
    assert rc == 2  # bad input, as README says
    assert "edge 0 crosses edge 2" in capsys.readouterr().err


@pytest.mark.parametrize("drones", ["0", "-2", "two"])
def test_cli_refuses_a_drone_count_below_one(tmp_path, capsys, drones):
    area = tmp_path / "a.json"
    area.write_text(json.dumps([[47.0, 8.0], [47.001, 8.0], [47.001, 8.001], [47.0, 8.001]]))
    with pytest.raises(SystemExit) as exit_:
        _main(["plan", str(area), "--swath", "20", f"--drones={drones}", "--out", str(tmp_path / "o")])
    last = capsys.readouterr().err.strip().splitlines()[-1]  # after argparse's usage lines
    assert exit_.value.code == 2 and "argument --drones:" in last and "--battery" not in last, last
    assert not (tmp_path / "o").exists()


def test_cli_needs_area_or_method(tmp_path, capsys):
    assert _main(["plan", "--swath", "20", "--alt", "30"]) == 2


def test_plan_search_reports_weak_fleet():
    area = SearchArea(vertices=[tuple(v) for v in U])
    weak = [DroneSpec(name="a", battery=0.1, endurance_s=600)]
    with pytest.raises(InsufficientCapabilityError):
        plan_search(area, weak, spacing_from_swath(20, 30), PlanConfig())
    with pytest.raises(InsufficientCapabilityError):
        plan_search(area, weak * 1, spacing_from_swath(20, 30), PlanConfig(division="region"))


def test_method_psa_is_dispatched(monkeypatch, tmp_path):
    calls = []

    class Fake:
        @staticmethod
        def add_arguments(parser):
            parser.add_argument("--targets")

        @staticmethod
        def run(args):
            calls.append(args.method)
            return 0

    monkeypatch.setattr(plan_cmd, "_plan_targets", Fake)
    assert _main(["plan", "--method", "psa"]) == 0
    assert _main(["plan", "--targets", "t.json"]) == 0  # --targets alone implies psa
    monkeypatch.setattr(plan_cmd, "_plan_targets", None)
    assert _main(["plan", "--method", "rsa"]) == 2
    assert calls == ["psa", "psa"]


@pytest.mark.parametrize("wind", [None, 90.0])
@pytest.mark.parametrize("shift", [-0.5, 0.2, 0.5])
def test_cli_curved_pattern_covers_the_concave_area(tmp_path, capsys, shift, wind):
    # At the CLI defaults (shift 0.2, no wind) the curved plan covered 91.9 % with 8 gaps
    # before legs all bent the same way and the line spacing allowed for the bend.
    area = tmp_path / "u.json"
    area.write_text(json.dumps(U))
    extra = [] if wind is None else ["--wind-from", str(wind)]
    rc = _main(
        [
            *["plan", str(area), "--pattern", "curved", "--shift", str(shift), "--swath", "30"],
            *["--alt", "40", "--drones", "2", "--out", str(tmp_path / "o"), *extra],
        ]
    )
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["coverage"]["covered_pct"] >= 99.999
    assert summary["coverage"]["gaps"] == 0
