"""Config: every shipped overlay loads, and out-of-range values are refused with one line."""

import subprocess
import sys
from pathlib import Path

import pytest

from lidar_slam.config import SlamConfig, load_config
from lidar_slam.errors import ConfigError, InputError

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("path", sorted((REPO / "configs").glob("*.yaml")), ids=lambda p: p.name)
def test_shipped_configs_load(path):
    """Every value the file sets is the loaded config's (and nothing is refused)."""
    import yaml

    cfg = load_config(path).model_dump()
    overlay = yaml.safe_load(path.read_text()) or {}

    def check(expected, got, where):
        if isinstance(expected, dict):
            for key, value in expected.items():
                check(value, got[key], f"{where}.{key}")
        else:
            assert got == expected, (where, got, expected)

    check(overlay, cfg, path.name)


@pytest.mark.parametrize("overlay,where", [
    ({"odometry": {"voxel_size_m": -1}}, "odometry.voxel_size_m"),
    ({"odometry": {"voxel_size_m": 0}}, "odometry.voxel_size_m"),
    ({"data": {"max_range_m": -5}}, "data.max_range_m"),
    ({"data": {"min_range_m": -1}}, "data.min_range_m"),
    ({"data": {"min_range_m": 50, "max_range_m": 40}}, "must exceed min_range_m"),
    ({"keyframes": {"distance_m": 0}}, "keyframes.distance_m"),
    ({"keyframes": {"cloud_voxel_m": -0.5}}, "keyframes.cloud_voxel_m"),
    ({"map": {"voxel_size_m": 0}}, "map.voxel_size_m"),
    ({"loop": {"scan_context": {"max_radius_m": -80}}}, "loop.scan_context.max_radius_m"),
    ({"loop": {"scan_context": {"rings": 0}}}, "loop.scan_context.rings"),
    ({"loop": {"verify": {"voxel_m": 0}}}, "loop.verify.voxel_m"),
    ({"loop": {"verify": {"min_fitness": 1.5}}}, "loop.verify.min_fitness"),
    ({"backend": {"odom_trans_sigma_m": 0}}, "backend.odom_trans_sigma_m"),
    ({"checkpoint": {"every_keyframes": -1}}, "checkpoint.every_keyframes"),
])
def test_out_of_range_values_are_refused(overlay, where):
    with pytest.raises(ConfigError, match=where.replace(".", r"\.")):
        load_config(None, overlay)


def test_zero_where_zero_means_off_is_accepted():
    cfg = load_config(None, {"data": {"min_range_m": 0}, "checkpoint": {"every_keyframes": 0},
                             "loop": {"verify": {"probe_shift_m": 0}},
                             "odometry": {"refine_below_mps": 0}})
    assert cfg.data.min_range_m == 0 and cfg.checkpoint.every_keyframes == 0
    assert cfg.loop.verify.probe_shift_m == 0 and cfg.odometry.refine_below_mps == 0


def test_negative_voxel_size_is_one_line_and_exit_2(tmp_path):
    """A run with voxel_size_m: -1 used to run (and find 3 loops instead of 5)."""
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("odometry:\n  voxel_size_m: -1\n")
    proc = subprocess.run([sys.executable, "-m", "lidar_slam.cli", "run",
                           str(REPO / "sample_scans"), "--out", str(tmp_path / "o"),
                           "--config", str(cfg)],
                          check=False, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "odometry.voxel_size_m" in lines[0] and "-1" in lines[0], lines
    assert not (tmp_path / "o").exists()


def test_default_yaml_lists_the_models_defaults():
    """configs/default.yaml is what the config models give without an overlay (regenerate it
    with dump_config(SlamConfig(), ...) when a key changes)."""
    import yaml

    from lidar_slam.config import SlamConfig

    path = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"
    assert yaml.safe_load(path.read_text()) == SlamConfig().model_dump()


@pytest.mark.parametrize("text", ["", "\n\n", "# only a comment\n", "---\n", "~\n"])
def test_an_empty_config_file_warns_and_gives_the_defaults(tmp_path, text, caplog):
    path = tmp_path / "c.yaml"
    path.write_text(text)
    assert load_config(path) == SlamConfig()
    assert f"{path}: config file is empty; using the defaults" in caplog.text


@pytest.mark.parametrize("text,needles", [
    ("- odometry\n- data\n", ["config must be a mapping of sections, not a list"]),
    ("odometry: {voxel_size_m: 0.5, voxel: 1}\n", ["odometry.voxel: Extra inputs"]),
    ("odometry: {max_points_per_voxel: many}\n",
     ["odometry.max_points_per_voxel: Input should be a valid integer", "(got 'many')"]),
    ("odometry: {voxel_size_m: .inf}\n", ["odometry.voxel_size_m: Input should be a finite"]),
    ("odometry: {voxel_size_m: 0.0001}\n",  # every point its own voxel: a wrong path, unsaid
     ["odometry.voxel_size_m: Input should be greater than or equal to 0.01", "(got 0.0001)"]),
    ("odometry: {max_num_iterations: 10000000000}\n", ["odometry.max_num_iterations"]),
    ("loop: 5\n", ["loop: Input should be a mapping of settings (got 5)"]),
    ("keyframes: {distance_m: true}\n", ["keyframes.distance_m: true is not a number"]),
    ("odometry: {max_num_threads: false}\n", ["odometry.max_num_threads: false is not a number"]),
    # a union's kinds each say what they want, and pydantic's tags stay out of the key
    ("keyframes: {distance_m: -1}\n",
     ["keyframes.distance_m: Input should be greater than 0; or Input should be 'auto'"]),
    ("1: {a: b}\n", ["1: Keys should be strings"]),
    ("data: {max_range_m: [1,\n", ["not valid YAML"]),
    ("when: 2023-02-30\n", ["not valid YAML (day is out of range for month)"]),
    ("imu: {enabled: true}\nodometry: {}\nimu: {enabled: false}\n",
     ["line 3: key 'imu' given twice (first on line 1)"]),
    ("data:\n  max_range_m: 50\n  max_range_m: 60\n", ["line 3: key 'max_range_m' given twice"]),
    ("data: {max_range_m: 5\nodometry: {}\n", ["line 2: not valid YAML"]),
])
def test_a_bad_config_file_is_one_line_naming_it(tmp_path, text, needles):
    """Not a mapping, unknown keys, wrong types, inf, C-int overflow and bad YAML: each one
    line that names the file (a top-level key that is a number raised a TypeError)."""
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises((ConfigError, InputError)) as err:
        load_config(path)
    line = str(err.value)
    assert "\n" not in line and line.startswith(f"{path}: "), line
    for needle in needles:
        assert needle in line, line


def test_a_config_that_still_sets_loop_following_is_one_line_naming_the_key(tmp_path):
    """Loop following (off by default, measured worse) is gone: an old overlay that still sets
    it gets the usual unknown-key line, not a silently ignored setting."""
    for text, key in (("loop: {follow_keyframes: 3}\n", "loop.follow_keyframes"),
                      ("loop: {verify: {follow_max_correction_m: 0.3}}\n",
                       "loop.verify.follow_max_correction_m")):
        path = tmp_path / "c.yaml"
        path.write_text(text)
        with pytest.raises(ConfigError) as err:
            load_config(path)
        line = str(err.value)
        assert "\n" not in line and line.startswith(f"{path}: {key}: Extra inputs"), line


def test_a_config_that_is_not_utf8_is_one_line(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_bytes(b"odometry:\n  voxel_size_m: \xff\n")
    with pytest.raises(InputError, match="c.yaml: not a text file"):
        load_config(path)


@pytest.mark.parametrize("text,hint", [
    ("odometry: {voxle_size_m: 0.5}\n", "(did you mean odometry.voxel_size_m?)"),
    ("imuu: {enabled: false}\n", "(did you mean imu?)"),
    ("loop: {verify: {coarse_voxel: 1.0}}\n", "(did you mean loop.verify.coarse_voxel_m?)"),
    ("data: {time_offset_s: 0.1}\n", "(did you mean imu.time_offset_s or gnss.time_offset_s?)"),
])
def test_a_config_typo_gets_the_closest_key(tmp_path, text, hint):
    """An unknown key names the closest one of its section (difflib), or the sections that
    have a key of that name; one line still."""
    path = tmp_path / "c.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(path)
    line = str(err.value)
    assert "\n" not in line and line.endswith(hint), line


def test_a_key_like_none_of_the_config_gets_no_guess(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("odometry: {zzzzqq: 1}\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert str(err.value).endswith("odometry.zzzzqq: Extra inputs are not permitted")
