"""Configuration: the defaults load, and every kind of bad value is rejected readably."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from sdh2svc.config import ConfigError, Settings, default_config_path, load_config
from sdh2svc.model.kinematics import Finger


def test_defaults_are_the_thesis_values() -> None:
    s = load_config(use_env=False)
    assert s.hand.proximal_length_mm == 86.5 and s.hand.base_offset_mm == 66.0
    assert (s.hand.distal_length_mm, s.hand.distal_length_schunk_mm) == (68.0, 68.5)
    r = s.rolling
    assert (r.delta_phi_deg, r.k, r.lambda_gain, r.alpha_deg) == (0.25, 2.0, 5.0, 22.0)
    assert (r.grasp_force, r.cycles) == (2, 3)
    # ΔΛ magnitudes of the thesis's §4.2 text (Table 8 swaps them; see config/default.toml)
    assert (r.delta_lambda_inc_mm, r.delta_lambda_dec_mm) == (0.1, 0.1)
    assert (s.axes.phi2, s.axes.phi3, s.axes.phi4, s.axes.phi5) == (1, 2, 5, 6)
    assert (s.axes.finger1_distal_matrix, s.axes.finger2_distal_matrix) == (1, 5)
    assert (s.tactile.distal.rows, s.tactile.distal.cols) == (13, 6)
    assert (s.tactile.proximal.rows, s.tactile.proximal.cols) == (14, 6)
    assert int(s.tactile.distal.valid().sum()) == 70  # thesis: 9 rows of 6 + 4 rows of 4
    assert s.calibration.pressure_per_count_n_per_mm2 == pytest.approx(0.000473 / 592.1)
    lim = s.finger_limits(Finger.TWO)
    assert (lim.proximal_min, lim.distal_max) == (-math.pi / 2, math.pi / 2)
    assert s.limits.min_deg[0] == 0.0 and s.limits.max_deg[0] == 90.0


def test_the_controller_gets_its_own_section() -> None:
    s = load_config(None, ["run.grasp_timeout_s=7"], use_env=False)
    c = s.control()
    assert (c.axes, c.limits, c.safety, c.rolling) == (s.axes, s.limits, s.safety, s.rolling)
    assert c.run == s.run and c.run.grasp_timeout_s == 7.0
    assert c.ctx == s.model_context()
    with pytest.raises(AttributeError):
        c.run = s.run  # type: ignore[misc]  # frozen


def test_default_file_exists_and_every_key_has_a_unit_or_comment() -> None:
    text = default_config_path().read_text()
    for line in text.splitlines():
        line = line.strip()
        if "=" in line and not line.startswith("#") and not line.startswith('"'):
            key = line.split("=")[0].strip()
            assert key.endswith(("_mm", "_deg", "_counts", "_n_per_mm2", "_rows")) or "#" in line, (
                f"{key!r} has neither a unit suffix nor a comment"
            )


def _problems(*overrides: str) -> str:
    with pytest.raises(ConfigError) as ei:
        load_config(overrides=overrides, use_env=False)
    return str(ei.value)


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ("rolling.k=0.5", ["rolling.k = 0.5", "greater than 1", "1.0 < k ≤ 10.0"]),
        ("rolling.alpha_deg=75", ["rolling.alpha_deg = 75", "0.0 < alpha_deg < 60.0"]),
        ("rolling.cycles=0", ["rolling.cycles = 0", "1 ≤ cycles ≤ 10000"]),
        ("rolling.delta_phi_deg=0", ["rolling.delta_phi_deg = 0", "must not be 0"]),
        ("rolling.delta_phi_deg=1e-300", ["rolling.delta_phi_deg", "at least 0.01° either way"]),
        ("rolling.d_sigma_deg=-0.001", ["rolling.d_sigma_deg", "at least 0.01° either way"]),
        ("rolling.k='fast'", ["rolling.k = 'fast'", "valid number"]),
        ("rolling.mode='three-finger'", ["rolling.mode", "'two-finger' or 'one-finger'"]),
        ("rolling.speed=3", ["rolling.speed", "unknown key (the keys there are: mode, route,"]),
        ("rollin.k=3", ["rollin (--set rollin.k=3): unknown key (the keys there are:", "rolling"]),
        ("run.watch_rate_hz=2", ["run.watch_rate_hz = 2", "a key no longer read", "drop it"]),
        ("limits.max_deg=[90, 90, 90, 90, 90, 90, 200]", ["limits.max_deg.6 = 200", "≤ 180.0"]),
        ("limits.min_deg=[0, 0]", ["limits.min_deg", "7"]),
        ("limits.min_deg=[0, 90, -90, -90, -90, -90, -90]", ["limits", "axes [1]"]),
        (
            "limits.min_deg=[0, -150, -90, -90, -90, -90, -90]",
            ["limits", "beyond the SDH2's own range (axis 1: -90…90°)", "never widen"],
        ),
        ("axes.phi4=1", ["axes", "exactly once"]),
        ("axes.phi2=9", ["axes.phi2 = 9", "0 ≤ phi2 ≤ 6"]),
        ("tactile.distal.mask=['######']", ["tactile.distal", "13 rows of 6"]),
        ("tactile.proximal.mask=" + str(["#x####"] * 14), ["tactile.proximal.mask", "'#'"]),
        ("calibration.distance.kind='table'", ["calibration.distance", "at least 2"]),
        ("calibration.cell_threshold_counts=5000", ["cell_threshold_counts = 5000", "≤ 4095"]),
        ("hand.pad.flat_end_x3_mm=10", ["hand.pad", "ordered"]),
        (
            "hand.proximal_length_mm=-1",
            ["hand.proximal_length_mm = -1", "0.0 < proximal_length_mm"],
        ),
    ],
)
def test_bad_values_are_named_with_value_and_range(override: str, expected: list[str]) -> None:
    msg = _problems(override)
    for fragment in expected:
        assert fragment in msg, msg


def test_several_problems_reported_together() -> None:
    with pytest.raises(ConfigError) as ei:
        load_config(overrides=["rolling.k=0", "rolling.alpha_deg=0"], use_env=False)
    assert len(ei.value.problems) == 2


def test_user_file_overrides_subset(tmp_path: Path) -> None:
    f = tmp_path / "lab.toml"
    f.write_text("[rolling]\nk = 5.0\ncycles = 7\n")
    s = load_config(f, use_env=False)
    assert (s.rolling.k, s.rolling.cycles, s.rolling.lambda_gain) == (5.0, 7, 5.0)


def test_user_file_errors_name_the_file(tmp_path: Path) -> None:
    f = tmp_path / "lab.toml"
    f.write_text("[rolling]\nk = 0.2\n")
    with pytest.raises(ConfigError, match=r"lab\.toml") as ei:
        load_config(f, use_env=False)
    assert "rolling.k = 0.2" in str(ei.value)
    f.write_text("[rolling\nk = ")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(f, use_env=False)
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "missing.toml", use_env=False)


def test_environment_and_override_precedence(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    f = tmp_path / "lab.toml"
    f.write_text("[rolling]\nk = 5.0\nlambda_gain = 4.0\n")
    monkeypatch.setenv("SDH2SVC_ROLLING__K", "3")
    s = load_config(f)
    assert s.rolling.k == 3.0  # environment beats the file
    assert s.rolling.lambda_gain == 4.0  # the file beats the defaults
    s = load_config(f, overrides=["rolling.k=4"])
    assert s.rolling.k == 4.0  # --set beats the environment
    monkeypatch.setenv("SDH2SVC_ROLLING__K", "0")
    with pytest.raises(ConfigError, match=r"rolling\.k = '0' \(SDH2SVC_ROLLING__K\)"):
        load_config(f)


def test_a_bad_value_names_the_layer_it_came_from(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """The file, the variable or the --set that gave the value, not the file for all."""
    f = tmp_path / "lab.toml"
    f.write_text("[rolling]\nk = 5.0\ncycles = 0\n")
    monkeypatch.setenv("SDH2SVC_ROLLING__LAMBDA_GAIN", "-1")
    with pytest.raises(ConfigError) as ei:
        load_config(f, overrides=["rolling.alpha_deg=90"])
    lines = ei.value.problems
    assert any(ln.startswith(f"rolling.cycles = 0 ({f})") for ln in lines), lines
    assert any(ln.startswith("rolling.lambda_gain = '-1' (SDH2SVC_ROLLING__LAMBDA_GAIN)")
               for ln in lines), lines  # fmt: skip
    assert any(ln.startswith("rolling.alpha_deg = 90 (--set rolling.alpha_deg=90)")
               for ln in lines), lines  # fmt: skip
    assert not any("rolling.k" in ln for ln in lines)  # 5.0 is fine
    # true, false and null quoted as the user wrote them (JSON, TOML), not as Python's repr
    with pytest.raises(ConfigError) as ei:
        load_config(overrides=["rolling.k=true"], use_env=False)
    assert ei.value.problems[0].startswith("rolling.k = true (--set rolling.k=true): ")
    # a check across fields names where its leading value came from too
    with pytest.raises(ConfigError) as ei:
        load_config(overrides=["rolling.grasp_force=5"], use_env=False)
    assert ei.value.problems[0].startswith(
        "rolling.grasp_force = 5 (--set rolling.grasp_force=5): its ceiling, "
    ), ei.value.problems


def test_environment_mistakes_are_named(monkeypatch: pytest.MonkeyPatch) -> None:
    """A misspelt section is refused (pydantic-settings would drop it); a list that is not
    JSON names its variable and says how to write one."""
    monkeypatch.setenv("SDH2SVC_ROLLNG__K", "3")
    with pytest.raises(ConfigError, match="SDH2SVC_ROLLNG__K: no such configuration section"):
        load_config()
    monkeypatch.delenv("SDH2SVC_ROLLNG__K")
    monkeypatch.setenv("SDH2SVC_SERVICE__ALLOWED_HOSTS", "labpc")
    with pytest.raises(ConfigError, match=r"SDH2SVC_SERVICE__ALLOWED_HOSTS = 'labpc'.*JSON"):
        load_config()
    monkeypatch.setenv("SDH2SVC_SERVICE__ALLOWED_HOSTS", '["labpc"]')
    monkeypatch.setenv("SDH2SVC_DEBUG", "1")  # the CLI's own switch, not configuration
    assert load_config().service.allowed_hosts == ("labpc",)


@pytest.mark.parametrize(
    ("overrides", "expected"),
    [
        (["run.preshape_deg=[nan,-30,30,-90,0,-30,30]"], "run.preshape_deg.0 = nan"),
        (["run.preshape_deg=[90,-30,30,-90,0,-30,170]"], "outside axis 6's joint limits"),
        (["limits.max_deg=[90,90,90,90,90,90,20]"], "run.preshape_deg.6 = 30: outside axis 6"),
        (
            ["run.grasp_min_velocity_deg_s=10", "run.grasp_max_velocity_deg_s=3"],
            "grasp_min_velocity_deg_s (10) must not exceed grasp_max_velocity_deg_s (3)",
        ),
        (
            ["run.grasp_approach_velocity_deg_s=4"],
            "grasp_approach_velocity_deg_s (4) must not exceed grasp_max_velocity_deg_s (3)",
        ),
        (
            ["service.port=8080", "service.viser_port=8080"],
            "service.port and service.viser_port are both 8080",
        ),
        (["sim.physics.pad_stiffness_n_per_mm3=inf"], "finite number"),
        (["sim.physics.gravity_m_per_s2=[0,nan,0]"], "gravity_m_per_s2.1 = nan"),
        (["sim.physics.gravity_m_per_s2=[-9.81,0,0]"], "out of the fingers' plane"),
        (["sim.physics.proximal_pad_start_mm=80"], "must be below proximal_pad_end_mm"),
        (["sim.object='nonsense'"], "unknown object 'nonsense' (the presets: rubber"),
        (['storage.db_path=""'], "storage.db_path = ''"),
        (["rolling.route=true"], "'thesis' or 'workspace'"),
        # no run parameter loosens a safety limit (the API changes run parameters)
        (
            ["rolling.grasp_force=4.5"],
            "rolling.grasp_force = 4.5 (--set rolling.grasp_force=4.5): its ceiling, "
            "safety.force_ceiling_factor × Fd = 13.5, is above safety.force_ceiling_max = 12",
        ),
        (["safety.force_ceiling_factor=4", "rolling.grasp_force=3.5"], "grasp_force ≤ 3:"),
        (["rolling.finger1_max_step_deg=1.5"], "above safety.max_step_deg = 1"),
        # a ceiling the pads cannot reach: a calibration that reads every force 185× lower
        (["calibration.force_reference_area_mm2=1"], "a saturated pad reads F = 0.229"),
        (["safety.force_ceiling_max=50"], "allowed: force_ceiling_max < 42.4"),
        (["safety.stale_frame_ms=2000"], "stale_frame_ms ≤ 1000"),
        # a finger must stop within one increment: every bound on motion rests on this one
        (["safety.max_step_deg=1.5"], "allowed: 0.0 < max_step_deg ≤ 1.0"),
        (["run.tactile_rate_hz=60"], "tactile_rate_hz ≤ 30"),  # the controller streams 30 at most
        (
            ["sim.links.dsa_tcp_port=47130", "sim.links.sdh_tcp_port=47130"],
            "sim.links.dsa_tcp_port and sdh_tcp_port are both 47130: one port each",
        ),
    ],
)
def test_values_that_would_mislead_the_hand_are_refused(
    overrides: list[str], expected: str
) -> None:
    """Values each field alone would take but the hand or the simulation cannot: a pre-shape
    beyond the joint limits (the motion clamps it to a limit without a word), NaN anywhere,
    settings that contradict each other, an object that is no preset."""
    with pytest.raises(ConfigError) as ei:
        load_config(overrides=overrides, use_env=False)
    assert expected in str(ei.value)


def test_bad_override_syntax() -> None:
    with pytest.raises(ConfigError, match=r"section\.key=value"):
        load_config(overrides=["rolling.k"], use_env=False)


def test_settings_are_immutable() -> None:
    s = load_config(use_env=False)
    with pytest.raises(ValueError, match="frozen"):
        s.rolling.k = 3.0  # type: ignore[misc]


def test_a_recording_older_than_a_key_or_a_limit_reads_back(cfg: Settings) -> None:
    """A run recorded before a key existed reads with today's value; one recorded under limits
    tightened since (stale_frame_ms 2000, a 50 Hz loop, a ceiling factor of 10 with Fd = 2)
    reads back as it was drawn — its pads, its hand, its pre-shape —, none of its safety
    limits or speeds taken in; a key this version does not know stays refused."""
    recorded = cfg.recorded()
    del recorded["calibration"]["spread_mm"]  # (a key an older version did not record)
    recorded["tactile"]["texel_pitch_mm"] = 3.5
    recorded["run"].update(preshape_deg=[10, 20, -20, 30, 20, -20, 30], tactile_rate_hz=50.0)
    recorded["safety"].update(stale_frame_ms=2000.0, force_ceiling_factor=10.0)
    # a measured table left with the linear map: refused in a configuration now, not in a
    # recording an older version made
    recorded["calibration"]["distance"] = {"kind": "linear", "table": [[0, 0], [40.8, 44]]}
    old = cfg.as_recorded(recorded)
    assert old.calibration.spread_mm == cfg.calibration.spread_mm
    assert old.tactile.texel_pitch_mm == 3.5 and old.run.preshape_deg[0] == 10
    assert old.run.tactile_rate_hz == cfg.run.tactile_rate_hz and old.safety == cfg.safety
    recorded["tactile"]["from_the_future"] = 1
    with pytest.raises(ConfigError, match=r"tactile\.from_the_future"):
        cfg.as_recorded(recorded)


def test_a_list_given_as_plain_text_is_told_how_to_write_it() -> None:
    """`--set service.allowed_hosts=labpc` said "Input should be a valid tuple" (CLI audit)."""
    with pytest.raises(ConfigError) as bad:
        load_config(overrides=["service.allowed_hosts=labpc"], use_env=False)
    said = "; ".join(bad.value.problems)
    assert 'a list is needed, written in JSON, e.g. service.allowed_hosts=["labpc"]' in said
    assert "tuple" not in said


def test_a_key_given_without_its_section_is_told_where_it_lives() -> None:
    """`--set db_path=…`: only "unknown key" and the sections (CLI audit)."""
    with pytest.raises(ConfigError) as bad:
        load_config(overrides=["db_path='/tmp/x.sqlite'"], use_env=False)
    assert "did you mean storage.db_path?" in "; ".join(bad.value.problems)


@pytest.mark.parametrize(
    ("override", "expected"),
    [
        ('service.allowed_hosts=["http://labpc:8000"]',
         "service.allowed_hosts.0 = 'http://labpc:8000' (--set service.allowed_hosts="
         '["http://labpc:8000"]): a host is name or name:port, without a scheme or a path: '
         "write 'labpc:8000'"),
        ('service.allowed_hosts=["labpc/dashboard"]', "write 'labpc'"),
        ('service.allowed_hosts=["labpc:http"]', "write 'labpc' or 'labpc:8000'"),
        ('service.allowed_origins=["labpc:8000"]',
         "service.allowed_origins.0 = 'labpc:8000' (--set service.allowed_origins="
         '["labpc:8000"]): an origin is scheme://host[:port], without a path: '
         "write 'http://labpc:8000'"),
        ('service.allowed_origins=["https://ops.example/app"]', "write 'https://ops.example'"),
    ],
)  # fmt: skip
def test_allowed_hosts_and_origins_that_could_never_match_are_refused(
    override: str, expected: str
) -> None:
    """A host with a scheme or a path, an origin without its scheme: accepted, they matched no
    request's Host or Origin, and the page they were for was refused (user audit)."""
    with pytest.raises(ConfigError) as bad:
        load_config(overrides=[override], use_env=False)
    assert expected in str(bad.value)


def test_allowed_hosts_and_origins_in_every_form_the_guard_matches() -> None:
    cfg = load_config(overrides=[
        'service.allowed_hosts=["Lab-PC.local", "proxy:8443", "[::1]:8000", "::1", "[fe80::1]"]',
        'service.allowed_origins=["https://ops.example:9443", "http://dash.example/", '
        '"http://[::1]:8000"]',
    ], use_env=False)  # fmt: skip
    assert cfg.service.allowed_hosts[1] == "proxy:8443"
    assert cfg.service.allowed_origins[1] == "http://dash.example/"
