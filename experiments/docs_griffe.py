"""A griffe extension for the site's API reference (mkdocs.yml, mkdocstrings' `extensions`): rdsexp's
docstrings are plain text with the paper's notation (`E[[1; xi][1; xi]^T]`, `x_{k|k}`, `A*B`), which
Markdown would read as reference links and emphasis. Outside inline code and indented blocks, the
characters Markdown gives a meaning there are escaped, so a docstring reads on the site as in the code.
"""
from __future__ import annotations

import re

import griffe

SPECIAL = re.compile(r"([\\\[\]*_<])")


def plain(text: str) -> str:
    """`text` with [ ] * _ < \\ escaped outside `code` spans and indented code blocks."""
    out, block, previous_blank = [], False, True
    for line in text.splitlines():
        blank = not line.strip()
        indented = line.startswith("    ")
        block = indented and (block or previous_blank) or (block and blank)
        if block or blank:
            out.append(line)
        else:
            parts = line.split("`")
            out.append("`".join(SPECIAL.sub(r"\\\1", part) if i % 2 == 0 else part for i, part in enumerate(parts)))
        previous_blank = blank
    return "\n".join(out)


class PlainDocstrings(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None:
            obj.docstring.value = plain(obj.docstring.value)
