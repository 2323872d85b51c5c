"""Tables for the terminal that never cut a word or a number: a rich table when every column
holds its longest word at the console's width, else key-value lines wrapped at spaces.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass, field

from rich.box import Box
from rich.console import Console
from rich.table import Table
from rich.text import Text

#: Below this console width (columns) every table is printed as key-value lines.
MIN_TABLE_WIDTH = 40


def _plain(cell: str) -> str:
    """A cell's text without rich markup."""
    return Text.from_markup(cell).plain


def _longest_word(text: str) -> int:
    return max((len(w) for w in text.split()), default=0)


@dataclass
class TextTable:
    """Rows of strings (rich markup allowed) under a title; ``columns``: the headings, the
    first naming the rows; ``header``: show them; ``right``: right-justified columns (default:
    all but the first); ``caption``: a line under the table; ``box``: rich's box."""

    title: str
    columns: tuple[str, ...]
    header: bool = True
    right: tuple[bool, ...] | None = None
    caption: str = ""
    box: Box | None = None
    rows: list[tuple[str, ...]] = field(default_factory=list)
    _sections: set[int] = field(default_factory=set)

    def add_row(self, *cells: str) -> None:
        if len(cells) != len(self.columns):
            raise ValueError(f"Expected {len(self.columns)} cells, got {len(cells)}")
        self.rows.append(tuple(str(c) for c in cells))

    def add_section(self) -> None:
        """A rule before the next row."""
        self._sections.add(len(self.rows))

    def fits(self, width: int) -> bool:
        """Whether a rich table of this width holds every word of every cell whole."""
        if width < MIN_TABLE_WIDTH:
            return False
        words = self._widths(_longest_word)
        # rich's heavy box: one border per column and one more, one space of padding per side
        return sum(words) + 3 * len(words) + 1 <= width

    def _one_line(self, width: int) -> bool:
        """Whether a rich table of this width holds every cell on one line."""
        full = self._widths(len)
        return sum(full) + 3 * len(full) + 1 <= width

    def print(self, console: Console) -> None:
        """Print as a table when it fits the console (a table without headings: when every
        row fits on one line), else as key-value lines."""
        if self._one_line(console.width) or (self.header and self.fits(console.width)):
            console.print(self._rich(console.width))
        else:
            for line in self.lines(console.width):
                console.print(line, highlight=False, markup=False, soft_wrap=True)

    def _widths(self, measure) -> list[int]:
        return [max([measure(_plain(r[j])) for r in self.rows]
                    + [measure(name) if self.header else 0], default=0)
                for j, name in enumerate(self.columns)]

    def _rich(self, width: int) -> Table:
        right = self.right or (False, *([True] * (len(self.columns) - 1)))
        table = Table(title=self.title, show_header=self.header, caption=self.caption or None,
                      **({} if self.box is None else {"box": self.box}))
        words, full = self._widths(_longest_word), self._widths(len)
        # wrap the first column (the rows' names) alone where the others fit whole
        whole = sum(full[1:]) + words[0] + 3 * len(full) + 1 <= width
        for j, name in enumerate(self.columns):
            if whole and j:
                table.add_column(name, justify="right" if right[j] else "left",
                                 min_width=full[j], no_wrap=True)
            else:
                table.add_column(name, justify="right" if right[j] else "left",
                                 min_width=words[j], overflow="fold")
        for i, row in enumerate(self.rows):
            if i in self._sections and i:
                table.add_section()
            table.add_row(*row)
        return table

    def lines(self, width: int) -> list[str]:
        """The key-value layout, wrapped at spaces to ``width`` (a word longer than the width
        stays whole on its own line)."""

        def wrap(text: str, indent: str) -> list[str]:
            return textwrap.wrap(text, width=max(width, 20), initial_indent=indent,
                                 subsequent_indent=indent + "    ", break_long_words=False,
                                 break_on_hyphens=False) or [indent.rstrip()]

        out = wrap(self.title, "") if self.title else []
        for row in self.rows:
            cells = [_plain(c) for c in row]
            if len(cells) == 2 and not self.header:
                out += wrap(f"{cells[0]}: {cells[1]}", "  ")
                continue
            out += wrap(cells[0] + ":", "  ")
            for name, value in zip(self.columns[1:], cells[1:], strict=True):
                if value:
                    out += wrap(f"{name}: {value}" if name else value, "    ")
        if self.caption:
            out += wrap(self.caption, "")
        return out
