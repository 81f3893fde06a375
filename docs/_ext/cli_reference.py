"""A Sphinx extension: the CLI reference, generated from the parsers the ``metadesign`` command builds (so it
cannot drift from the code).  Directive ``.. metadesign-cli::`` (MyST: a ``{metadesign-cli}`` block)
renders every command's ``--help`` with a section per command, in the order ``metadesign --help`` lists them;
each section is a label (``metadesign-library-coupling-check``), which the results page's ``{reproduce}``
role links to.
"""
from __future__ import annotations

import argparse
import os

from docutils import nodes
from docutils.parsers.rst import Directive


def _walk(parser: argparse.ArgumentParser, prefix: str):
    yield prefix, parser
    for act in parser._actions:  # argparse offers no public walk over sub-commands
        if isinstance(act, argparse._SubParsersAction):
            seen = set()
            for name, sub in act.choices.items():
                if id(sub) in seen:  # aliases
                    continue
                seen.add(id(sub))
                yield from _walk(sub, f"{prefix} {name}")


def command_helps() -> list[tuple[str, str]]:
    """(command, help text) for ``metadesign`` and each sub-command, help formatted at 100 columns."""
    from metadesign.cli import build_parser

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        return [(name, p.format_help()) for name, p in _walk(build_parser(), "metadesign")]
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


class MetadesignCli(Directive):
    has_content = False

    def run(self):
        out = []
        for name, text in command_helps():
            label = nodes.make_id(name)
            sec = nodes.section(ids=[label], names=[label])
            sec += nodes.title(text=name)
            sec += nodes.literal_block(text, text)
            self.state.document.note_explicit_target(sec)  # a label: {ref}`metadesign-library-peds`
            out.append(sec)
        return out


def setup(app):
    app.add_directive("metadesign-cli", MetadesignCli)
    return {"version": "1", "parallel_read_safe": True}
