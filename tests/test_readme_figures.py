"""benchmarks/readme.py and its record: the README's block and the docs agree with the record, and
--check's comparison flags a moved figure (driven by fake commands; no benchmark runs here)."""

import json

import pytest

from benchmarks import readme

RECORD = readme.load(readme.RECORD)


def test_readme_block_is_what_write_makes():
  assert readme.block_of((readme.ROOT / "README.md").read_text()) == readme.render(RECORD)


def test_every_figure_names_its_file_its_command_or_why_and_its_noise():
  ids = [f["id"] for f in RECORD["figures"]]
  assert len(ids) == len(set(ids))
  sections = {s["id"] for s in RECORD["sections"]}
  for f in RECORD["figures"]:
    assert (readme.ROOT / f["file"]).is_file(), f["id"]
    assert f.get("section") in sections or "text" in f, f["id"]  # in README's block, or quoted
    if f["command"] is None:
      assert f["why"], f["id"]
    else:
      assert f["minutes"] > 0 and "tolerance" in f and "machine" in f, f["id"]
      assert f.get("read") is not None or f.get("device") == "gpu", f["id"]


def test_every_figure_text_is_in_its_file_with_its_recorded_value():
  assert [p for p in readme.docs_problems(RECORD, readme.ROOT) if not p.startswith("README.md:")] \
      == []


def test_the_optimise_seed_spread_is_over_seeds_of_the_documented_command():
  (f,) = [f for f in RECORD["figures"] if f["id"] == "optimise_lidar_test8"]
  assert f["command"].startswith("python evaluate.py --dataset synthetic_lidar:8 --split test "
                                 "--method optimise --seed {seed}")
  assert len(f["seeds"]) >= 3


STEADY = "python -c \"print('epe 0.5')\""
DRIFTED = "python -c \"import json; json.dump({'a': [{'b': 0.9}]}, open('{out}/r.json', 'w'))\""
SEEDED = "python -c \"print('v', {seed})\""


def _fake_record(tmp_path):
  """A record of three fake figures (a regex, a JSON key, a spread over seeds), a README holding
  its block and a doc quoting one of them."""
  figures = [
    dict(id="steady", file="README.md", section="s", label="steady", command=STEADY,
         read={"regex": r"epe ([\d.]+)"}, minutes=1, value=0.5, format="{:.2f}",
         tolerance={"abs": 0.01}, machine="m", pairs=1),
    dict(id="drifted", file="doc.md", text="the doc says 0.70 m", command=DRIFTED,
         read={"json": "r.json", "key": ["a", 0, "b"]}, minutes=1, value=0.7, format="{:.2f}",
         tolerance={"rel": 0.1, "abs": 0.01}, machine="m"),
    dict(id="seeded", file="README.md", section="s", label="over seeds", command=SEEDED,
         read={"regex": r"v ([\d.]+)"}, seeds=[1, 2, 6], minutes=1, value=None, stale=True,
         format="{:.0f}", tolerance={"abs": 0.5}, machine=None, pairs=2),
  ]
  record = {"sections": [{"id": "s", "title": "Fake"}], "figures": figures}
  path = tmp_path / "figures.json"
  readme.save(record, path)
  (tmp_path / "README.md").write_text(f"# x\n\n{readme.BEGIN}\n{readme.render(record)}\n"
                                      f"{readme.END}\n\nafter\n")
  (tmp_path / "doc.md").write_text("Here the doc says\n0.70 m of it.\n")
  return path


def _main(capsys, *argv):
  try:
    readme.main(list(argv))
    code = 0
  except SystemExit as e:
    code = e.code
  return code, capsys.readouterr().out


def test_check_passes_an_unmoved_figure(tmp_path, capsys):
  path = _fake_record(tmp_path)
  code, out = _main(capsys, "--check", "--only", "steady", "--figures", str(path),
                    "--root", str(tmp_path))
  assert code in (0, None), out
  assert "steady: ok" in out


def test_check_names_a_moved_figure_and_one_never_measured(tmp_path, capsys):
  path = _fake_record(tmp_path)
  code, out = _main(capsys, "--check", "--figures", str(path), "--root", str(tmp_path))
  assert code == 1
  failed = out.split("FAILED:")[1]
  assert "drifted (doc.md): recorded 0.7, measured 0.9" in failed
  assert "seeded (README.md): no recorded value" in failed
  assert "steady" not in failed


def test_record_writes_the_values_and_the_block_then_check_passes(tmp_path, capsys):
  path = _fake_record(tmp_path)
  code, out = _main(capsys, "--record", "--only", "seeded,drifted", "--figures", str(path),
                    "--root", str(tmp_path))
  assert code in (0, None), out
  figures = {f["id"]: f for f in json.loads(path.read_text())["figures"]}
  assert figures["seeded"]["value"]["median"] == 2 and figures["seeded"]["value"]["worst"] == 6
  assert set(figures["seeded"]["value"]["per_seed"]) == {"1", "2", "6"}
  assert "stale" not in figures["seeded"] and figures["drifted"]["value"] == 0.9
  assert "median 2, worst 6" in (tmp_path / "README.md").read_text()  # the block followed
  assert "to mend by hand: drifted" in out  # doc.md still says 0.70
  (tmp_path / "doc.md").write_text("Here the doc says 0.90 m of it.\n")
  figures["drifted"]["text"] = "the doc says 0.90 m"
  readme.save({"sections": [{"id": "s", "title": "Fake"}], "figures": list(figures.values())},
              path)
  code, out = _main(capsys, "--check", "--figures", str(path), "--root", str(tmp_path))
  assert code in (0, None), out


def test_check_fails_on_a_block_written_by_hand(tmp_path, capsys):
  path = _fake_record(tmp_path)
  text = (tmp_path / "README.md").read_text()
  (tmp_path / "README.md").write_text(text.replace("| 0.50 |", "| 0.49 |"))
  code, out = _main(capsys, "--check", "--only", "steady", "--figures", str(path),
                    "--root", str(tmp_path))
  assert code == 1 and "README.md: its figures block is not what --write makes" in out


@pytest.mark.parametrize("value, got, moves", [
  (0.5, 0.505, False), (0.5, 0.53, True), ([1.0, 2.0], 1.5, False), ([1.0, 2.0], 2.3, True),
  ({"median": 1.0, "worst": 2.0}, {"median": 1.0, "worst": 2.05}, False),
  ({"median": 1.0, "worst": 2.0}, {"median": 1.2, "worst": 2.0}, True)])
def test_moved_compares_with_the_larger_of_its_bounds(value, got, moves):
  figure = {"value": value, "tolerance": {"abs": 0.01, "rel": 0.05}}
  assert (readme.moved(figure, got) is not None) == moves


def test_list_names_every_figure(capsys):
  code, out = _main(capsys, "--list")
  assert code in (0, None)
  assert all(f"{f['id']}  [" in out for f in RECORD["figures"])
  assert "--check:" in out
