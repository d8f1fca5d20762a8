"""TensorBoard event files of a training run, beside metrics.jsonl (the flax examples' convention):

    tensorboard --logdir runs/          # every run of the folder, each its own line

`train/*` (loss, grad_norm, param_norm, lr, pairs_per_s) at every logged step, `eval/*` (the five
metrics) at every held-out evaluation and at the end, `eval/pair_*` the Fig. 2 view
(jaxflow.viz.figures) of the first held-out pairs with the model's flow. Written by tensorboardX (no
TensorFlow), read back by `read_events`.
"""

import math
import pathlib
import struct
import tempfile


PICTURES = 2  # held-out pairs drawn at each evaluation


class EventWriter:
  """Scalars and PNG pictures into WORKDIR/events.out.tfevents.* (`enabled` False: processes
  other than 0 write nothing)."""

  def __init__(self, logdir, enabled: bool = True):
    self.logdir, self.enabled, self._writer = pathlib.Path(logdir), enabled, None

  def _file_writer(self):
    if self._writer is None:
      from tensorboardX import SummaryWriter  # pylint: disable=import-outside-toplevel
      self._writer = SummaryWriter(str(self.logdir), flush_secs=30)
    return self._writer

  def scalars(self, step: int, record: dict, prefix: str, skip=("step", "stage", "time")):
    """The finite numbers of `record` as PREFIX/NAME at `step`."""
    if not self.enabled:
      return
    writer = self._file_writer()
    for name, value in record.items():
      if name not in skip and isinstance(value, (int, float)) and not isinstance(value, bool) \
          and math.isfinite(value):
        writer.add_scalar(f"{prefix}/{name}", float(value), step)

  def pictures(self, step: int, pairs, prefix: str = "eval"):
    """The Fig. 2 view of each (name, pc1, pc2, flow, gt, mask) as PREFIX/pair_I at `step`."""
    if not self.enabled or not pairs:
      return
    from tensorboardX.proto.summary_pb2 import Summary  # pylint: disable=import-outside-toplevel
    from jaxflow.viz import figures  # pylint: disable=import-outside-toplevel  (matplotlib: only here)

    values = []
    with tempfile.TemporaryDirectory() as tmp:
      for i, (name, pc1, pc2, flow, gt, mask) in enumerate(pairs):
        path = pathlib.Path(tmp) / f"{i}.png"
        figures.render_pair(pc1, pc2, flow, path, gt=gt, title=f"{name} (step {step})", mask=mask)
        png = path.read_bytes()
        width, height = struct.unpack(">II", png[16:24])  # the PNG header's IHDR chunk
        values.append(Summary.Value(tag=f"{prefix}/pair_{i}", image=Summary.Image(
          height=height, width=width, colorspace=4, encoded_image_string=png)))
    self._file_writer().file_writer.add_summary(Summary(value=values), step)

  def flush(self):
    if self._writer is not None:
      self._writer.flush()

  def close(self):
    if self._writer is not None:
      self._writer.close()
      self._writer = None


def read_events(logdir) -> dict:
  """{tag: [(step, value)]} of every event file under `logdir` (scalars: float; pictures: PNG
  bytes), read from the files' records (length, CRC, Event proto, CRC) with tensorboardX's protos."""
  from tensorboardX.proto.event_pb2 import Event  # pylint: disable=import-outside-toplevel

  found = {}
  for path in sorted(pathlib.Path(logdir).glob("events.out.tfevents.*")):
    data = path.read_bytes()
    offset = 0
    while offset + 12 <= len(data):
      (length,) = struct.unpack("<Q", data[offset:offset + 8])
      event = Event.FromString(data[offset + 12:offset + 12 + length])
      offset += 12 + length + 4
      for value in event.summary.value:
        kind = value.WhichOneof("value")
        got = value.simple_value if kind == "simple_value" else (
          value.image.encoded_image_string if kind == "image" else None)
        if got is not None:
          found.setdefault(value.tag, []).append((event.step, got))
  return found
