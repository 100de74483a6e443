"""mkdocs hook: every page's rendered blocks are rendered from their result files (or from the
code) when the site is built, with the same functions as ``python docs/results.py render``."""

from __future__ import annotations

import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location(
    "docs_results", Path(__file__).with_name("results.py")
)
results = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(results)


def on_page_markdown(markdown: str, **kwargs) -> str:
    return results.render_text(markdown)
