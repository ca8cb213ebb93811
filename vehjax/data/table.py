"""Text tables as spreadsheets, loggers and pandas export them, read with the standard `csv` module.

:func:`read_table` reads a delimited text file with a header row into named text columns and
:func:`parse_cells` turns a column of cells into floats. What is accepted, and why:

* Encoding: UTF-8, with or without a byte-order mark (Excel's "CSV UTF-8" writes one), or
  UTF-16 with its byte-order mark (Excel's "Unicode Text"). Any other encoding is refused with
  the byte offset where decoding failed (pass ``encoding=``).
* Line ends: LF, CRLF or CR, as the ``csv`` module reads them.
* Separator: ``delimiter`` when given, else sniffed (``csv.Sniffer``) among ``,`` ``;`` tab ``|``
  from the first lines, falling back to the one that splits the header into the most fields.
* Quoting: fields and headers in double quotes (``"t [s]"``, also after a space following the
  separator), a doubled quote inside.
* Blank lines anywhere (before the header, between rows, at the end) and rows whose every field
  is empty (a spreadsheet's empty row, ``,,,``) are skipped: they hold no time stamp.
* Trailing separators: empty fields after the last named column, on the header or on any row
  (a logger that ends every line with the separator), are dropped without a word; a value in
  such a field is an error (it has no column name).
* Names: stripped of surrounding spaces; an empty name before the last named column (pandas'
  ``to_csv`` writes its index so unless ``index=False``) and a name given twice are refused,
  naming their positions.

Cells: numbers as Python's ``float`` reads them (``1.5``, ``-2e-3``, `` 7 ``, ``inf``); a cell
in :data:`MISSING` (compared after stripping spaces) is a missing sample, NaN; anything else
(``n/a``, ``-``, ``1.234,5``) is refused naming the column, the data row (1-based, blank rows not
counted) and the file line. With ``decimal=","`` a decimal comma is read as a point (a cell
holding a point as well is refused: thousands separators are not read).
"""

from __future__ import annotations

import codecs
import csv
import io
import math
from dataclasses import dataclass

import numpy as np

__all__ = ["MISSING", "Table", "read_table", "parse_cells", "is_missing"]

#: Cells that mean "no sample" (compared after stripping spaces; "nan" in any letter case):
#: an empty cell (pandas' ``to_csv`` default for NaN), ``nan`` / ``NaN`` (Python, numpy) and
#: ``NA`` (R's ``write.csv``). Everything else that is not a number is an error.
MISSING = ("", "nan", "NA")

_CANDIDATES = ",;\t|"


def is_missing(cell: str) -> bool:
    """Whether a text cell is a missing sample (one of :data:`MISSING`)."""
    s = cell.strip()
    return s == "" or s == "NA" or s.lower() == "nan"


@dataclass(frozen=True)
class Table:
    """A text table: ``names`` (header, stripped), ``cells`` name -> list of text cells,
    ``lines`` the file line (1-based) of each data row, and the ``delimiter`` used."""

    names: list
    cells: dict
    lines: list
    delimiter: str


def _decode(path, data: bytes, encoding) -> str:
    if data.startswith(b"PK\x03\x04"):
        raise ValueError(f"path: {str(path)!r} is a zip archive (an Excel workbook?), not a text "
                         f"table: save it as 'CSV UTF-8' or read it with pandas.read_excel")
    if encoding is None:
        if data.startswith((codecs.BOM_UTF16_LE, codecs.BOM_UTF16_BE)):
            encoding = "utf-16"
        else:
            encoding = "utf-8-sig"               # strips Excel's byte-order mark
    try:
        text = data.decode(encoding)
        return text[1:] if text.startswith("\ufeff") else text   # a mark under encoding=
    except UnicodeDecodeError as exc:
        shown = "UTF-8" if encoding == "utf-8-sig" else encoding
        raise ValueError(f"path: {str(path)!r} is not {shown} text (byte {exc.start}: "
                         f"{data[exc.start:exc.start + 1]!r}); save it as UTF-8 ('CSV UTF-8' "
                         f"in Excel) or pass encoding=, e.g. encoding='cp1252'") from None
    except LookupError:
        raise ValueError(f"encoding: unknown encoding {encoding!r}") from None


def _sniff(lines: list) -> str:
    """The separator of a table from its first non-blank lines (header first)."""
    sample = "\n".join(lines[:20])
    try:
        found = csv.Sniffer().sniff(sample, delimiters=_CANDIDATES).delimiter
        if found and found in _CANDIDATES:
            return found
    except csv.Error:
        pass
    counts = {d: len(next(csv.reader([lines[0]], delimiter=d))) for d in _CANDIDATES}
    best = max(counts, key=counts.get)
    return best if counts[best] > 1 else ","


def _header(path, row: list) -> list:
    names = [h.strip() for h in row]
    while names and names[-1] == "":              # trailing separators
        names.pop()
    if not names:
        raise ValueError(f"path: {str(path)!r} has no header row")
    for i, n in enumerate(names):
        if n == "":
            raise ValueError(
                f"path: {str(path)!r}: column {i + 1} of the header has no name (pandas' "
                f"to_csv writes its index so: write with index=False, or name the column)")
    seen = {}
    for i, n in enumerate(names):
        if n in seen:
            raise ValueError(f"path: {str(path)!r}: the header names {n!r} twice (columns "
                             f"{seen[n] + 1} and {i + 1}); give every column its own name")
        seen[n] = i
    return names


def read_table(path, delimiter: str | None = None, encoding: str | None = None) -> Table:
    """The header names and text cells of a delimited text file (see the module docstring).

    ``delimiter``: the separator, None to sniff it. ``encoding``: None reads UTF-8 (with or
    without a byte-order mark) or UTF-16 with a byte-order mark. Raises ValueError naming the
    file for an undecodable file, no header, an unnamed or duplicated column, a row with more
    or fewer fields than the header names (naming its line).
    """
    if delimiter is not None and (not isinstance(delimiter, str) or len(delimiter) != 1):
        raise ValueError(f"delimiter: expected one character or None to sniff, got {delimiter!r}")
    with open(path, "rb") as fh:
        text = _decode(path, fh.read(), encoding)
    present = [ln for ln in io.StringIO(text, newline=None) if ln.strip()]
    if not present:
        raise ValueError(f"path: {str(path)!r} has no header row")
    delim = _sniff([ln.rstrip("\r\n") for ln in present]) if delimiter is None else delimiter
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delim, skipinitialspace=True)
    names, rows, lines = None, [], []
    for row in reader:
        if not any(f.strip() for f in row):       # blank line or a row of empty fields
            continue
        if names is None:
            names = _header(path, row)
            continue
        width = len(names)
        if len(row) > width and any(f.strip() for f in row[width:]):
            extra = next(f for f in row[width:] if f.strip())
            raise ValueError(f"path: {str(path)!r} line {reader.line_num}: {len(row)} fields but "
                             f"the header names {width} columns ({extra!r} has no column name; "
                             f"separator {delim!r})")
        if len(row) < width:
            raise ValueError(f"path: {str(path)!r} line {reader.line_num}: {len(row)} fields, "
                             f"expected {width} like the header (separator {delim!r})")
        rows.append(row[:width])
        lines.append(reader.line_num)
    cells = {n: [r[i] for r in rows] for i, n in enumerate(names)}
    return Table(names=names, cells=cells, lines=lines, delimiter=delim)


def _number(cell: str, decimal: str) -> float:
    s = cell.strip()
    if decimal != ".":
        if "." in s:
            raise ValueError(cell)
        s = s.replace(decimal, ".")
    return float(s)


def parse_cells(column: str, cells, where, decimal: str = ".", delimiter: str = ",") -> np.ndarray:
    """Text ``cells`` as floats, :data:`MISSING` ones as NaN.

    ``where(k)`` names data row ``k`` (0-based) at the start of the message, e.g.
    "path: 'a.csv', data row 3, line 5".
    ValueError naming ``column``, the row and the cell for anything else; with the hint to pass
    ``decimal=","`` (naming the file's ``delimiter``) when the cell reads as a number with a
    decimal comma.
    """
    if decimal == ".":
        try:                                      # every cell a number: numpy reads them at once
            return np.array(cells, dtype=float)
        except ValueError:
            pass
    out = np.empty(len(cells))
    for k, cell in enumerate(cells):
        if is_missing(cell):
            out[k] = math.nan
            continue
        try:
            out[k] = _number(cell, decimal)
        except ValueError:
            hint = ""
            if decimal == "." and "," in cell and "." not in cell:
                try:
                    _number(cell, ",")
                    hint = (f"; the file is separated by {delimiter!r} and the cell reads as a "
                            f"number with a decimal comma: pass decimal=','")
                except ValueError:
                    pass
            raise ValueError(f"{where(k)}: not a number in column {column!r}: {cell!r} (a missing "
                             f"sample is an empty cell, 'nan' or 'NA'){hint}") from None
    return out
