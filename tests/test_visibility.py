"""jaxflow.geometry.visibility: what a sensor at the origin saw, on a hand-built cloud."""

import numpy as np
import pytest

from jaxflow.geometry import visibility

# Returns before a y-up sensor looking along z: a cross at 10 m, one far return (the view reaches 40
# m); and the points asked about, with what each is.
RETURNS = [[0.0, 0.0, 10.0], [1.0, 0.0, 10.0], [-1.0, 0.0, 10.0], [0.0, 1.0, 10.0],
           [0.0, -1.0, 10.0], [0.5, 0.0, 40.0]]
ASKED = {(0.0, 0.0, 5.0): visibility.SEEN,  # before the return
         (0.0, 0.0, 10.3): visibility.SEEN,  # on it
         (0.0, 0.0, 12.0): visibility.HIDDEN,  # behind it
         (0.5, 0.5, 10.0): visibility.SEEN,  # inside the view, no return there (empty)
         (5.0, 0.0, 10.0): visibility.OUTSIDE,  # beyond the view's edge
         (0.0, 0.0, 41.0): visibility.OUTSIDE}  # beyond its range


@pytest.mark.parametrize("up", ["y", "z"])
def test_seen_hidden_and_outside(up):
  to_axes = (lambda p: p) if up == "y" else (lambda p: p[:, [2, 0, 1]])  # z up: x forward
  view = visibility.View(to_axes(np.array(RETURNS)), up)
  asked = to_axes(np.array(list(ASKED)))
  assert view.state(asked).tolist() == list(ASKED.values())
  # Occlusion alone: the point beyond the range is behind the 10 m return too.
  assert view.hidden(asked).tolist() == [False, False, True, False, False, True]


def test_a_sensor_away_from_the_frames_origin():
  """A vehicle frame: the sensor 1.7 m above and 1.4 m behind the origin (y up, z forward). Seen
  from the sensor the states are those above; seen from the origin the returns no longer lie
  before the points they hide."""
  sensor = np.array([0.0, 1.7, -1.4])
  returns, asked = np.array(RETURNS) + sensor, np.array(list(ASKED)) + sensor
  view = visibility.View(returns, "y", origin=sensor)
  assert view.state(asked).tolist() == list(ASKED.values())
  assert not visibility.View(returns, "y").hidden(asked)[2]
