"""jaxflow.lidar.settings: the raw-sweep pipeline's settings, from Python (raw_sweep_flow,
predict_flow) and from predict's command line (--method.lidar.FIELD, --print_config)."""

import dataclasses
import os
import re

import numpy as np
import pytest

from jaxflow import evaluate, inference, predict as predict_command
from jaxflow.data import synthetic_sweep as ss
from jaxflow.errors import ConfigError, DataError
from jaxflow.lidar import ego, settings as lidar_settings, sweep
from jaxflow.methods import lidar as lidar_method, registry
from jaxflow.runtime import configfile

import commands

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Restrictive: no object may turn or be searched for beyond the fine search's 0.5 m, and no slow
# motion is kept by the evidence.
STILL = {"max_yaw_deg_per_s": 0.0, "search.per_s": 0.0, "judge.margin": 1.0,
         "judge.evidence": 0.0}  # none beats still


def test_the_per_second_settings_at_10_hz_are_the_per_frame_numbers():
  config = lidar_settings.Sweep()
  rate = config.frame_rate_hz
  assert rate == 10.0 and config.max_range == 35.0
  assert config.objects.search.per_s / rate == 3.5  # metres a frame
  assert config.objects.max_yaw_deg_per_s / rate == 10.0  # degrees a frame
  for field, frame in (("yaw_deg_per_s", np.arange(-6.0, 6.01, 1.0)),
                       ("x_per_s", np.arange(-4.0, 4.01, 0.5)),
                       ("y_per_s", np.arange(-1.5, 1.51, 0.5))):
    lowest, highest, step = (v / rate for v in getattr(config.ego.search, field))
    np.testing.assert_array_equal(np.arange(lowest, highest + step / 2, step), frame)
    assert ego.search_grid(getattr(config.ego.search, field), rate).tobytes() == frame.tobytes()
  np.testing.assert_array_equal(ego.search_grid(config.ego.search.x_per_s, 20.0),
                                np.arange(-2.0, 2.01, 0.25))  # a 20 Hz sensor: half as far


@pytest.fixture(scope="module")
def pair():
  return ss.sweep_pair("val", 2, ss.Options(scale=0.2))  # ~21k points, 4 moving objects found


def changed(frame_rate_hz=10.0, objects=None):
  """The default settings at `frame_rate_hz`, with `objects` {dotted field of the objects block:
  value} (as the command line's --method.lidar.objects.FIELD)."""
  fields = {f"objects.{k}": v for k, v in (objects or {}).items()}
  return configfile.replace_settings(lidar_settings.Sweep(frame_rate_hz=frame_rate_hz), fields,
                                     "method.lidar")


@pytest.fixture(scope="module")
def flows(pair):
  """raw_sweep_flow's (flow, info) of the pair with the default settings and with STILL's."""
  return {"default": sweep.raw_sweep_flow(None, pair.pc1, pair.pc2),
          "still": sweep.raw_sweep_flow(None, pair.pc1, pair.pc2, settings=changed(objects=STILL))}


def test_a_setting_changes_the_flow_through_the_api(pair, flows):
  (flow, info), (still, still_info) = flows["default"], flows["still"]
  assert len(info.objects.moved) >= 2 and info.settings == lidar_settings.Sweep()
  assert still_info.settings.objects.max_yaw_deg_per_s == 0.0
  assert len(still_info.objects.moved) < len(info.objects.moved)
  assert np.abs(still - flow).max() > 1.0  # the movers' flows are gone
  # At 1000 Hz the same per-second limits are 0.1 deg and 3.5 cm a frame: fewer objects move.
  fast = sweep.raw_sweep_flow(None, pair.pc1, pair.pc2, settings=changed(1000.0))[1]
  assert len(fast.objects.moved) < len(info.objects.moved)
  settings = changed(objects=STILL)  # the pipeline's: the lidar method's, running no method
  predictor = inference.load_predictor(method="lidar", method_settings=settings)
  api = inference.predict_flow(pair.pc1, pair.pc2, predictor=predictor, up="z")
  assert settings.objects.max_yaw_deg_per_s == 0.0  # read, not changed
  np.testing.assert_array_equal(api, still)


def test_a_ground_setting_reaches_every_ground_mask(pair, flows):
  """ground.margin (the surfaces carry it): more points are ground in both sweeps, and the
  masks the pictures draw are those counted."""
  base = lidar_settings.Sweep()
  config = dataclasses.replace(base, ground=dataclasses.replace(base.ground, margin=0.6))
  _, wide = sweep.raw_sweep_flow(None, pair.pc1, pair.pc2, settings=config)
  default = flows["default"][1]
  assert wide.ground[0] > default.ground[0] and wide.ground[1] > default.ground[1]
  assert [int(m.sum()) for m in wide.ground_masks] == list(wide.ground)


def predict(*args):
  """`python -m jaxflow.predict ARGS`, run in this process (tests/commands.py)."""
  return commands.run(predict_command.run, *args)


@pytest.fixture(scope="module")
def runs(tmp_path_factory, pair):
  """predict's command lines, one after another in this process: --lidar with and without --sweep
  overrides, --print_config, an unknown field."""
  d = tmp_path_factory.mktemp("sweeps")
  np.save(d / "a.npy", pair.pc1)
  np.save(d / "b.npy", pair.pc2)
  lidar = (d / "a.npy", d / "b.npy", "--lidar")
  procs = {
    "default": predict(*lidar, "--out", d / "default.npy"),
    "still": predict(*lidar, "--out", d / "still.npy",
                     *(f"--method.lidar.objects.{k}={v}" for k, v in STILL.items())),
    "print_config": predict("--print_config", "--lidar", "--method.optimise.rigid_steps=3",
                            "--method.lidar.objects.max_yaw_deg_per_s=5"),
    "nope": predict(*lidar, "--out", d / "nope.npy", "--method.lidar.objects.nope=1"),
    "old": predict(*lidar, "--out", d / "old.npy", "--sweep.objects.cell=0.2"),
    "other": predict(d / "a.npy", d / "b.npy", "--out", d / "other.npy",
                     "--method.lidar.objects.cell=0.2"),
  }
  out = {k: (p.stdout, p.stderr, p.returncode) for k, p in procs.items()}
  return d, out


@pytest.mark.slow  # it reads the `runs` fixture (every command line at once)
def test_predict_sweep_flags_change_the_flow(runs, flows):
  d, out = runs
  for name in ("default", "still"):
    assert out[name][2] == 0, out[name][1][-2000:]
  default, still = np.load(d / "default.npy"), np.load(d / "still.npy")
  assert np.abs(still - default).max() > 1.0
  nothing = re.compile(r"\b0 of \d+ candidate objects move")
  assert nothing.search(out["still"][1]) and not nothing.search(out["default"][1])
  np.testing.assert_allclose(still, flows["still"][0], atol=1e-5)  # the flags are the settings
  np.testing.assert_allclose(default, flows["default"][0], atol=1e-5)


def _field_paths(block, prefix=""):
  """Every leaf field of a settings dataclass, dotted."""
  out = []
  for f in dataclasses.fields(block):
    value = getattr(block, f.name)
    out += (_field_paths(value, f"{prefix}{f.name}.") if dataclasses.is_dataclass(value)
            else [prefix + f.name])
  return out


@pytest.mark.slow
def test_print_config_lists_the_sweep_settings_with_units(runs):
  stdout, stderr, rc = runs[1]["print_config"]
  assert rc == 0, stderr[-2000:]
  lines = [l for l in stdout.splitlines() if l.startswith("method.lidar.")]
  fields = _field_paths(lidar_method.Lidar())  # the pipeline's and the method it runs
  assert len(lines) == len(fields) > 50
  assert any(l.startswith("config.eval.") for l in stdout.splitlines())  # and the first config
  assert "method.optimise.rigid_steps = 3" in stdout  # --lidar --method X: X's settings too
  for field in fields:
    (line,) = [l for l in lines if l.startswith(f"method.lidar.{field} = ")]
    assert "  # " in line, line  # every field has its comment
  assert ("method.lidar.objects.max_yaw_deg_per_s = 5.0  # deg/s: an object turning faster is "
          "refused" in lines)  # the override applied
  assert ("method.lidar.objects.search.per_s = 35.0  # m/s: an object's translation search, +- "
          "this" in lines)
  assert any(l.startswith("method.lidar.frame_rate_hz = 10.0  # ") for l in lines)


@pytest.mark.slow
@pytest.mark.parametrize("run, says", [
  ("nope", "method.lidar.objects.nope: no field 'nope' in Objects"),
  ("old", "--sweep.objects.cell is now --method.lidar.objects.cell"),
  ("other", "--method.lidar.* sets the lidar method's settings, but the method is optimise"),
])
def test_a_wrong_sweep_field_is_one_line_and_exit_2(runs, run, says):
  _, stderr, rc = runs[1][run]
  assert rc == 2
  errors = [l for l in stderr.splitlines() if l.startswith("error:")]
  assert len(errors) == 1 and says in errors[0], stderr
  assert "Traceback" not in stderr


def test_a_bad_value_is_refused_naming_its_field():
  with pytest.raises(ValueError, match=r"lidar objects\.cell must be a finite number >= 0, got -"):
    lidar_settings.Objects(cell=-0.3)
  with pytest.raises(ValueError, match=r"lidar ego\.gicp\.iterations must be an integer >= 0, "):
    lidar_settings.Gicp(iterations=2.5)
  with pytest.raises(ValueError, match=r"lidar ground\.surface\.windows must be"):
    lidar_settings.GroundSurface(windows=(5, float("nan")))
  with pytest.raises(ValueError, match="lidar objects.person.top must be"):
    lidar_settings.Person(top=(1.0,))
  with pytest.raises(ValueError, match="lidar frame_rate_hz must be > 0"):
    lidar_settings.Sweep(frame_rate_hz=0.0)
  lidar_settings.Ground(min_sensor_height=-2.0)  # signed fields may be negative
  with pytest.raises(DataError, match=r"pc1: raw_sweep_flow takes N x 3 points, got shape \(10, "):
    sweep.raw_sweep_flow(None, np.zeros((10, 4)), np.zeros((10, 3)))
  with pytest.raises(Exception, match="jaxflow.lidar.settings.Sweep"):
    sweep.raw_sweep_flow(None, np.zeros((10, 3)), np.zeros((10, 3)), settings={"max_range": 5})


def test_a_sub_blocks_field_is_set_by_its_dotted_path():
  """--method.lidar.objects.person.radius=0.6 (the command line's string) reaches the objects
  block's Person, the rest left at their defaults; a bad value is refused naming the flag."""
  chosen = registry.settings("lidar", fields={"objects.person.radius": "0.6",
                                              "objects.icp.scales": "(0.3, 0.1)"})
  assert chosen.objects.person == lidar_settings.Person(radius=0.6)
  assert chosen.objects.icp == lidar_settings.Icp(scales=(0.3, 0.1))
  assert chosen.objects.search == lidar_settings.Search() and chosen.objects.cell == 0.3
  with pytest.raises(ConfigError, match=r"^method\.lidar\.objects\.person\.radius: lidar "
                     r"objects\.person\.radius must be a finite number >= 0, got -1\.0$"):
    registry.settings("lidar", fields={"objects.person.radius": "-1"})
  with pytest.raises(ConfigError, match=r"objects\.person_radius: no field 'person_radius'"):
    registry.settings("lidar", fields={"objects.person_radius": "0.6"})  # the flat name is gone


@pytest.mark.parametrize("path, value, block, bad, flat", [
  ("ground.surface.cell", "1.0", lidar_settings.GroundSurface(cell=1.0), "-1",
   "ground.surface_cell"),
  ("ground.up_check.planes", "200", lidar_settings.UpCheck(planes=200), "-1",
   "ground.up_check_planes"),
  ("ego.gicp.iterations", "20", lidar_settings.Gicp(iterations=20), "-1", "ego.gicp_iterations"),
  ("ego.search.x_per_s", "(-30.0, 30.0, 5.0)", lidar_settings.EgoSearch(x_per_s=(-30.0, 30.0, 5.0)),
   "(1.0, 2.0)", "ego.search_x_per_s"),
  ("objects.judge.hidden_fit", "0.4", lidar_settings.Judge(hidden_fit=0.4), "-1",
   "objects.hidden_fit"),
])
def test_the_ground_ego_and_judge_blocks_are_set_by_their_dotted_paths(path, value, block, bad,
                                                                       flat):
  """--method.lidar.ground.surface.cell=1.0 and the like reach their block, the rest left at
  their defaults; a bad value is refused naming the flag; the old flat name is refused."""
  def replaced(settings, dotted, value):
    head, _, rest = dotted.partition(".")
    inner = replaced(getattr(settings, head), rest, value) if rest else value
    return dataclasses.replace(settings, **{head: inner})

  chosen = registry.settings("lidar", fields={path: value})
  assert chosen == replaced(registry.settings("lidar"), path.rsplit(".", 1)[0], block)
  with pytest.raises(ConfigError, match=rf"^method\.lidar\.{re.escape(path)}: lidar "
                     rf"{re.escape(path)} must be "):
    registry.settings("lidar", fields={path: bad})
  old = flat.rsplit(".", 1)[1]
  with pytest.raises(ConfigError, match=rf"{re.escape(flat)}: no field '{old}'"):
    registry.settings("lidar", fields={flat: value})


def test_every_setting_is_checked_by_its_own_block():
  """Each field of each block refuses a value of no kind in its block's __post_init__, naming the
  setting by its path under the lidar method (lidar objects.person.radius)."""

  def blocks(cls, path):
    yield cls, path
    for f in dataclasses.fields(cls):
      if dataclasses.is_dataclass(f.default):
        yield from blocks(type(f.default), f"{path}{f.name}.")

  for cls, path in blocks(lidar_settings.Sweep, "lidar "):
    for f in dataclasses.fields(cls):
      with pytest.raises(ValueError, match=re.escape(f"{path}{f.name} must be")):
        cls(**{f.name: "x"})


def test_evaluate_takes_the_lidar_methods_fields():
  """evaluate.py --method lidar --method.lidar.FIELD=V (README): the field set, as --print_config
  lists it; a lidar field with another method is refused."""
  run = lambda *args: commands.run(evaluate.run, *args, cwd=ROOT,  # `python evaluate.py ARGS`
                                   prog=commands.script("evaluate.py"))
  given = run("--method", "lidar", "--method.lidar.objects.person.size=0.9", "--print_config")
  assert given.returncode == 0, given.stderr[-2000:]
  assert "method.lidar.objects.person.size = 0.9  # " in given.stdout
  assert "method.lidar.objects.cell = 0.3  # " in given.stdout
  other = run("--method", "network", "--method.lidar.max_range=20", "--print_config")
  assert other.returncode == 2 and "the method is network" in other.stderr
