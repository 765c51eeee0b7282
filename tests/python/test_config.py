"""YAML configuration: commented defaults that load back unchanged, merging, and clear errors."""

from __future__ import annotations

import dataclasses
import pickle
from dataclasses import dataclass

import numpy as np
import pytest
import terracube as tc
import yaml
from terracube.cli import app
from terracube.config import (
    SECTIONS,
    Config,
    ConfigError,
    FrameParams,
    default_config,
    dump_config,
    load_config,
    register_section,
)
from terracube.mapping import MapperParams
from typer.testing import CliRunner

EXPECTED_SECTIONS = {
    "frame": FrameParams,
    "collapse": tc.CollapseParams,
    "elevation": tc.ElevationParams,
    "terrain": tc.TerrainParams,
    "fuzzy": tc.FuzzyParams,
    "registration": tc.RegistrationParams,
    "pcl_icp": tc.PclIcpParams,
    "mapper": MapperParams,
}


def _write(tmp_path, text: str, name: str = "robot.yaml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_the_defaults_are_the_dataclass_defaults():
    config = default_config()
    assert list(config) == list(EXPECTED_SECTIONS)
    for name, params_type in EXPECTED_SECTIONS.items():
        assert config[name] == params_type(), name
        assert getattr(config, name) == params_type()


def test_the_dumped_yaml_holds_every_field_but_the_frame_ones_and_a_comment_per_section():
    text = dump_config()
    data = yaml.safe_load(text)
    assert list(data) == list(EXPECTED_SECTIONS)
    for name, params_type in EXPECTED_SECTIONS.items():
        fields = {f.name for f in dataclasses.fields(params_type)}
        if name in ("collapse", "elevation"):  # transform and crop come from the frame section
            fields -= {"transform", "crop"}
        if name == "mapper":  # from the terrain and registration sections
            fields -= {"terrain", "registration"}
        assert set(data[name]) == fields, name
        assert f"\n# {name}: " in text
    # the comments are the dataclasses' own attribute docs
    assert "  # Cube edge E [m], > 0.\n  edge: 0.5\n" in text
    assert "  # Sensor height above the ground [m]" in text
    assert data["registration"]["class_weights"] == {
        "obstacle": 0.8,
        "overhanging_object": 0.5,
        "vertical_object": 0.5,
        "horizontal_edge": 0.8,
    }


def test_the_printed_defaults_load_back_to_the_same_parameters(tmp_path):
    path = _write(tmp_path, dump_config())
    assert load_config(path) == default_config()


def test_a_changed_configuration_round_trips_through_yaml(tmp_path):
    config = (
        default_config()
        .replace("frame", roll_deg=2.5, crop=[[-10.0, -10.0, -3.0], [10.0, 10.0, 5.0]])
        .replace("collapse", edge=0.25, sigma=5, storage="sparse")
        .replace("elevation", resolution=0.2, origin=[-5.0, -5.0], size=[50, 50])
        .replace("terrain", reference="local_ground", sensor_height=1.73)
        .replace("fuzzy", membership="gaussian", extent=[[0.0, -5.0], [20.0, 5.0]], ridge=1e-7)
        .replace("registration", class_weights={tc.TerrainClass.OBSTACLE: 1.0}, degeneracy_threshold=1e-9)
    )
    loaded = load_config(_write(tmp_path, dump_config(config)))
    assert loaded == config
    assert loaded != default_config()
    assert loaded.fuzzy.ridge == 1e-7 and loaded.registration.degeneracy_threshold == 1e-9
    assert loaded.registration.class_weights == {tc.TerrainClass.OBSTACLE: 1.0}
    assert loaded.elevation.size == [50, 50] and isinstance(loaded.elevation.size[0], int)


def test_a_file_gives_only_what_it_changes(tmp_path):
    path = _write(tmp_path, "collapse:\n  edge: 0.25\nterrain:\n  sensor_height: 1.73\nfuzzy:\n")
    config = load_config(path)
    assert config.collapse == tc.CollapseParams(edge=0.25)
    assert config.terrain == tc.TerrainParams(sensor_height=1.73)
    assert config.elevation == tc.ElevationParams()
    assert load_config(_write(tmp_path, "", "empty.yaml")) == default_config()
    assert load_config(None) == default_config()


def test_whole_numbers_and_yaml_1_1_exponents_are_read_as_floats(tmp_path):
    config = load_config(_write(tmp_path, "collapse:\n  edge: 1\nfuzzy:\n  ridge: 1e-6\n  epochs: 4.0\n"))
    assert config.collapse.edge == 1.0 and isinstance(config.collapse.edge, float)
    assert config.fuzzy.ridge == 1e-6
    assert config.fuzzy.epochs == 4 and isinstance(config.fuzzy.epochs, int)


@pytest.mark.parametrize(
    "text, message",
    [
        ("colapse:\n  edge: 0.3\n", r"unknown section 'colapse'; did you mean 'collapse'\?"),
        ("collapse:\n  egde: 0.3\n", r"unknown key in section 'collapse' 'egde'; did you mean 'edge'\?"),
        ("collapse:\n  edge: fast\n", r"collapse\.edge must be a number, got 'fast' \(str\)"),
        ("collapse:\n  sigma: 2.5\n", r"collapse\.sigma must be a whole number, got 2\.5"),
        ("collapse:\n  drop_non_finite: 1\n", r"collapse\.drop_non_finite must be true or false"),
        ("collapse:\n  storage: 3\n", r"collapse\.storage must be a string"),
        ("collapse:\n  storage: compact\n", r"section 'collapse': storage must be one of"),
        ("collapse:\n  crop: [[0, 0, 0], [1, 1, 1]]\n", r"'crop' is not read in section 'collapse'.*'frame'"),
        ("terrain:\n  reference: nowhere\n", r"section 'terrain': reference must be one of"),
        (
            "registration:\n  class_weights: {trees: 1.0}\n",
            r"registration\.class_weights must be a mapping of one of unknown, ground, .* to numbers",
        ),
        ("elevation:\n  size: [10, ten]\n", r"elevation\.size must be a list of whole numbers or null"),
        ("elevation:\n  origin: [0, 0]\n", r"section 'elevation': give both origin and size"),
        ("frame:\n  crop: [1, 2, 3]\n", r"frame\.crop must be a list of lists of numbers or null"),
        (
            "collapse:\n  sensor_origin: [0, 1.8]\n",
            r"collapse\.sensor_origin must be a list of 3 numbers or null",
        ),
        ("frame:\n  crop: [[1, 2, 3]]\n", r"section 'frame': crop must be \[\[xmin"),
        ("frame:\n  crop: [[1, 0, 0], [0, 1, 1]]\n", r"min corner \[1\.0, 0\.0, 0\.0\] exceeds"),
        ("collapse: 0.5\n", r"section 'collapse' must be a mapping of keys, got float"),
        ("- collapse\n", r"expected a mapping of sections"),
        ("collapse:\n  edge: [0.5\n", r"not valid YAML at line \d+, column \d+"),
    ],
)
def test_a_bad_file_names_itself_and_the_problem(tmp_path, text, message):
    path = _write(tmp_path, text, "bad_robot.yaml")
    with pytest.raises(ConfigError, match=r"bad_robot\.yaml: .*" + message):
        load_config(path)


@pytest.mark.parametrize(
    "text, message",
    [
        ("collapse:\n  edge: -1\n", r"section 'collapse': edge must be a positive finite length in metres"),
        (
            "collapse:\n  ground_support: 12\n",
            r"section 'collapse': shadow_aware ground_support must be 1\.\.9",
        ),
        ("collapse:\n  bottom_window: 0\n", r"section 'collapse': shadow_aware bottom_window must be 1\.\.8"),
        (
            "collapse:\n  free_margin: .nan\n",
            r"section 'collapse': shadow_aware free_margin_m must be a finite",
        ),
        (
            "elevation:\n  resolution: 0\n",
            r"section 'elevation': resolution must be a positive finite length",
        ),
        (
            "terrain:\n  std_dev: -0.1\n",
            r"section 'terrain': ground height, std-dev and robot height thresholds",
        ),
        ("fuzzy:\n  rules_x: 1\n", r"section 'fuzzy': a fuzzy elevation map needs at least 2 x 2 rules"),
        ("registration:\n  search_window: -1\n", r"section 'registration': correlative search window_m"),
        ("mapper:\n  keyframe_distance: 0\n", r"section 'mapper': MapperParams\.keyframe_distance_m must be"),
    ],
)
def test_values_the_core_refuses_are_refused_when_the_file_is_read(tmp_path, text, message):
    """The ranges live in the C++ checks (``check_*_params``); a file is checked against them at
    load time, naming the file and section, not at the first scan of a run."""
    path = _write(tmp_path, text, "bad_robot.yaml")
    with pytest.raises(ConfigError, match=r"bad_robot\.yaml: " + message):
        load_config(path)


@pytest.mark.skipif(not tc.has_pcl(), reason="this build has no PCL baseline")
def test_a_negative_pcl_epsilon_is_refused_when_the_file_is_read(tmp_path):
    path = _write(tmp_path, "pcl_icp:\n  transformation_epsilon: -1\n", "bad_robot.yaml")
    with pytest.raises(ConfigError, match=r"bad_robot\.yaml: section 'pcl_icp': .*epsilons must be finite"):
        load_config(path)


def test_a_missing_file_is_a_config_error_naming_it(tmp_path):
    with pytest.raises(ConfigError, match=r"nothing\.yaml: no such configuration file"):
        load_config(tmp_path / "nothing.yaml")


def test_one_more_section_registers_with_one_line(tmp_path):
    @dataclass
    class PlannerParams:
        """Test stand-in for a later stage's parameters.

        Attributes
        ----------
        keyframe_distance : float
            A new keyframe every this many metres.
        loop_closing : bool
            Close loops.
        """

        keyframe_distance: float = 2.0
        loop_closing: bool = True

    try:
        register_section("planner", PlannerParams, "Planner: chaining classified maps.")
        text = dump_config()
        assert "# planner: Planner: chaining classified maps.\nplanner:\n" in text
        assert "  # A new keyframe every this many metres.\n  keyframe_distance: 2.0\n" in text
        config = load_config(_write(tmp_path, "planner:\n  keyframe_distance: 5\n"))
        assert config.planner == PlannerParams(keyframe_distance=5.0)
        assert load_config(_write(tmp_path, text, "all.yaml")) == default_config()
        with pytest.raises(ValueError, match="already registered"):
            register_section("planner", PlannerParams, "again")
    finally:
        SECTIONS.pop("planner", None)


def test_replace_ignores_none_and_the_config_is_immutable_and_picklable():
    config = default_config().replace("collapse", edge=0.3, sigma=None)
    assert config.collapse == tc.CollapseParams(edge=0.3)
    with pytest.raises(AttributeError, match="immutable"):
        config.collapse = tc.CollapseParams()
    with pytest.raises(KeyError, match="unknown section 'nope'"):
        config.replace("nope", edge=1.0)
    assert pickle.loads(pickle.dumps(config)) == config  # Dask workers receive it pickled
    assert isinstance(pickle.loads(pickle.dumps(config)), Config)


def test_the_frame_gives_the_leveling_transform_and_crop_box():
    frame = FrameParams(roll_deg=3.0, pitch_deg=-2.0, crop=[[0, 0, 0], [1, 2, 3]])
    expected = tc.leveling_transform(np.radians(3.0), np.radians(-2.0))
    np.testing.assert_array_equal(frame.transform(), expected)
    assert frame.crop_box() == ((0.0, 0.0, 0.0), (1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match="roll_deg must be a finite angle"):
        FrameParams(roll_deg=float("nan"))


# ------------------------------------------------------------------------------------ command line


def test_terracube_config_prints_yaml_that_loads_back_to_the_defaults(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["config"])
    assert result.exit_code == 0, result.output
    assert load_config(_write(tmp_path, result.stdout)) == default_config()
    result = runner.invoke(app, ["config", "--output", str(tmp_path / "out" / "terracube.yaml")])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "out" / "terracube.yaml").read_text() == dump_config()


def test_terracube_config_merges_and_checks_a_file(tmp_path):
    runner = CliRunner()
    result = runner.invoke(app, ["config", "-c", str(_write(tmp_path, "collapse:\n  sigma: 7\n"))])
    assert result.exit_code == 0
    assert yaml.safe_load(result.stdout)["collapse"]["sigma"] == 7
    result = runner.invoke(app, ["config", "-c", str(_write(tmp_path, "colapse: {}\n", "typo.yaml"))])
    assert result.exit_code == 2
    assert "typo.yaml" in result.output and "did you mean 'collapse'" in result.output


def _scan(tmp_path):
    rng = np.random.default_rng(5)
    ground = np.c_[rng.uniform(0, 10, (3000, 2)), rng.normal(0, 0.02, 3000)]
    canopy = np.c_[rng.uniform(2, 5, (600, 2)), rng.uniform(1.3, 1.6, 600)]
    points = np.vstack([ground, canopy])
    path = tmp_path / "scan.npy"
    np.save(path, points)
    return path, points


def test_options_override_the_file_and_the_file_overrides_the_defaults(tmp_path):
    """The canopy 1.3 m up is an overhang for sigma 2 at E = 0.25 m but not for sigma 4 at E = 0.5 m."""
    path, points = _scan(tmp_path)
    config = _write(tmp_path, "collapse:\n  edge: 0.25\n  sigma: 2\n")
    runner = CliRunner()
    cases = {
        "file": (["-c", str(config)], 0.25, 2),
        "flag": (["-c", str(config), "--edge", "0.5", "--sigma", "4"], 0.5, 4),
        "robot": (["-c", str(config), "--robot-height", "1.0"], 0.25, 4),  # ceil(1.0 / 0.25)
        "defaults": ([], 0.5, 2),
    }
    for case, (args, edge, sigma) in cases.items():
        out = tmp_path / case
        result = runner.invoke(app, ["collapse", str(path), "-o", str(out), "-f", "npz", "--no-png", *args])
        assert result.exit_code == 0, result.output
        expected = tc.collapse_overhangs(points, edge, sigma).overhang
        np.testing.assert_array_equal(np.load(out / "scan_classified.npz")["overhang"], expected, case)
        assert f"edge {edge} m, sigma {sigma} cubes" in result.output
    assert np.load(tmp_path / "file" / "scan_classified.npz")["overhang"].sum() > 400  # most of the canopy
    assert np.load(tmp_path / "flag" / "scan_classified.npz")["overhang"].sum() == 0


@pytest.mark.parametrize("command", ["collapse", "dem", "classify", "fem"])
def test_every_stage_refuses_a_bad_config_file_naming_it(tmp_path, command):
    path, _ = _scan(tmp_path)
    config = _write(tmp_path, "collapse:\n  edge: wide\n", "wrong.yaml")
    result = CliRunner().invoke(app, [command, str(path), "-o", str(tmp_path), "-c", str(config)])
    assert result.exit_code == 2
    assert "wrong.yaml" in result.output and "collapse.edge must be a number" in result.output


# Hostile files (issue 39): a clear ConfigError in well under a second, never a hang or a traceback.

_ALIAS_BOMB = (
    "collapse:\n  edge: [&a [x,x,x,x,x,x,x,x,x]"
    + "".join(f", &{chr(98 + i)} [" + ",".join([f"*{chr(97 + i)}"] * 9) + "]" for i in range(8))
    + "]\n"
)  # 9^9 = 387,420,489 strings when expanded, in 300 bytes


@pytest.mark.parametrize(
    "text, message",
    [
        (
            "collapse:\n  edge: 0.1\n  edge: 0.2\n",
            "line 3, column 3: duplicate key 'edge' \\(first at line 2\\)",
        ),
        ("collapse: {edge: 0.1}\ncollapse: {sigma: 1}\n", "line 2, column 1: duplicate key 'collapse'"),
        ("collapse:\n  edge: " + "[" * 20000 + "]" * 20000 + "\n", "nested deeper than 64 levels"),
        ("".join("  " * i + "- \n" for i in range(2000)), "nested deeper than 64 levels"),
        (_ALIAS_BOMB, r"collapse.edge must be a number, got \[\[.*\.\.\."),
    ],
    ids=["duplicate-key", "duplicate-section", "deep-flow", "deep-block", "alias-bomb"],
)
def test_a_hostile_file_is_a_short_config_error(tmp_path, text, message):
    path = tmp_path / "hostile.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=message) as caught:
        load_config(path)
    assert str(caught.value).startswith(f"{path}: ") and len(str(caught.value)) < 300
