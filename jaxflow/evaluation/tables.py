"""Markdown tables for what the tools print: one formatter for every table."""


def markdown_table(header, rows) -> str:
  """A Markdown table: the first column left-aligned, the others right-aligned (numbers).

  `header`: column titles; `rows`: sequences of cells (already formatted strings, or values str()
  turns into the cell)."""
  lines = [tuple(map(str, header))] + [tuple(map(str, row)) for row in rows]
  if any(len(line) != len(header) for line in lines):
    raise ValueError(f"every row needs {len(header)} cells")
  widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
  fmt = lambda line: "| " + " | ".join(c.ljust(w) if i == 0 else c.rjust(w)
                                       for i, (c, w) in enumerate(zip(line, widths))) + " |"
  rule = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
  return "\n".join([fmt(lines[0]), rule] + [fmt(line) for line in lines[1:]])
