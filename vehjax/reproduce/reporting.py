"""What the reproductions' reports share: markdown tables, the report's title and figure links,
``report.md`` itself, run counts, timings and the small helpers of their figures.

The studies (``dutta2019``, ``wang2016``, ``consistency``) write their own tables; this module
holds only what they write the same way, so that a change to it (a column rule, how a
figure is linked, what "diverged" says) reaches every report at once.
"""

from __future__ import annotations

import time
from pathlib import Path

# ----------------------------------------------------------------------------------------------
# markdown


def md_row(cells) -> str:
    """One markdown table row: ``| a | b |``."""
    return "| " + " | ".join(str(c) for c in cells) + " |"


def md_rule(n: int) -> str:
    """The rule under a markdown table's header of ``n`` columns: ``|---|---|``."""
    return "|" + "---|" * n


def md_table(head, rows) -> str:
    """A markdown table: the header ``head`` (column names), its rule, then ``rows`` (each a
    sequence of cells, one per column)."""
    head = list(head)
    return "\n".join([md_row(head), md_rule(len(head))] + [md_row(r) for r in rows])


def title(name: str, paper: str) -> str:
    """The first block of a reproduction's ``report.md``: its command and the paper."""
    return f"# vehjax reproduce {name}\n\n{paper}.\n"


def figure_link(path, caption: str) -> str:
    """A markdown image link to ``path`` (a figure written next to ``report.md``), with a
    blank line after it."""
    return f"![{caption}]({Path(path).name})\n"


def write_report(out_dir, text: str) -> Path:
    """Write ``text`` to ``out_dir / "report.md"``; its path."""
    path = Path(out_dir) / "report.md"
    path.write_text(text)
    return path


def pm(mean, std, digits: int) -> str:
    """``mean +- std`` with ``digits`` decimals."""
    return f"{mean:.{digits}f} +- {std:.{digits}f}"


def runs_text(runs: int, diverged: int) -> str:
    """'10 runs' or '10 runs, 2 diverged run(s) left out' (figure titles)."""
    return f"{runs} runs" + (f", {diverged} diverged run(s) left out" if diverged else "")


def split_names(text, lower: bool = False) -> tuple:
    """The names of a comma-separated option (blanks dropped, order kept; lower-cased with
    ``lower``). The caller checks them against what it allows and names the option."""
    names = (v.strip() for v in str(text).split(","))
    return tuple(v.lower() if lower else v for v in names if v)


# ----------------------------------------------------------------------------------------------
# timing


def timed(fn, *args, **kwargs):
    """``(fn(*args, **kwargs), wall seconds)``; the seconds include compilation when ``fn``
    compiles."""
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    return out, time.perf_counter() - t0


# ----------------------------------------------------------------------------------------------
# figures


def window_steps(t, seconds: float) -> int:
    """Steps of a moving window of ``seconds`` on the uniform time grid ``t`` (at least 1)."""
    return max(1, int(round(seconds / (t[1] - t[0])))) if len(t) > 1 else 1


def line_width(k: int, n: int, thin: float, extra: float) -> float:
    """Width of the ``k``-th of ``n`` overlapping lines, the first thickest (``thin + extra``)
    down to ``thin``: lines that coincide stay visible."""
    return thin + extra * (n - 1 - k) / max(1, n - 1)
