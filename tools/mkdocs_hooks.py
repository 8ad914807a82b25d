"""MkDocs hook: publish the committed results (``results/**/*.md``, ``*.png``) under the same paths in the site.

The ablation's pages and plots live in ``results/`` beside the runs that wrote them (``python -m agents.ablation
... --summarize-only`` rewrites them); the docs link to them as ``results/ablation/...`` without copying them.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mkdocs.structure.files import File, Files

SUFFIXES = (".md", ".png")


def on_files(files: Files, config: Any) -> Files:
    root = Path(config.config_file_path).resolve().parent
    for path in sorted((root / "results").rglob("*")):
        if path.is_file() and path.suffix in SUFFIXES:
            rel = path.relative_to(root).as_posix()
            files.append(File(rel, str(root), config.site_dir, config.use_directory_urls))
    return files
