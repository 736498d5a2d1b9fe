"""MkDocs hook (mkdocs.yml: `hooks:`): the pages' LaTeX math, `$...$` inline and `$$...$$` on lines of their own,
turned into MathML when the site is built (`latex2mathml`). Browsers render MathML themselves, so the site needs no
script or font from the network and reads offline. Code (fenced blocks, inline code spans) is left as it is: a
shell's `$run` is no formula.
"""
from __future__ import annotations

import re

# fenced blocks (``` or ~~~, possibly indented in a list) and inline code spans: never math
CODE = re.compile(r"^[ \t]*(```+|~~~+)[^\n]*\n.*?^[ \t]*\1[ \t]*$|(`+)(?:(?!\2).)+?\2", re.M | re.S)
DISPLAY = re.compile(r"\$\$(.+?)\$\$", re.S)
INLINE = re.compile(r"(?<![\\$\w])\$(?![\s$])(.+?)(?<![\s\\])\$(?![\w$])")


def mathml(text: str) -> str:
    """A page's Markdown with its formulas (outside code) as MathML."""
    from latex2mathml.converter import convert

    def formulas(part: str) -> str:
        part = DISPLAY.sub(lambda m: convert(m.group(1).strip(), display="block"), part)
        return INLINE.sub(lambda m: convert(m.group(1)), part)

    out, start = [], 0
    for code in CODE.finditer(text):
        out += [formulas(text[start:code.start()]), code.group(0)]
        start = code.end()
    return "".join(out + [formulas(text[start:])])


def on_page_markdown(markdown: str, **kwargs) -> str:
    return mathml(markdown)
