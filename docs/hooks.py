"""MkDocs hook: the ten module folders' READMEs (and their pictures) are the site's module pages.

Each ``N_word/README.md`` becomes ``modules/N_word/README.md`` (served as that folder's index), its ``*.png`` beside
it, so the READMEs stay the one source and their links work both on GitHub and on the site: ``gui.png`` and
``../2_odm_runner/README.md`` as they are, ``../docs/page.md`` rewritten to ``../../page.md``.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.structure.files import File

MODULE_PAGE = re.compile(r"^modules/\d_\w+/README\.md$")


def on_files(files, config):
    """Add every module folder's README and pictures to the site's files."""
    root = Path(config["config_file_path"]).parent
    for readme in sorted(root.glob("[0-9]_*/README.md")):
        for path in [readme, *sorted(readme.parent.glob("*.png"))]:
            src = f"modules/{readme.parent.name}/{path.name}"
            files.append(File.generated(config, src, abs_src_path=str(path)))
    return files


def on_page_markdown(markdown, page, config, files):
    """A module README's links into docs/ point to the site's pages."""
    if MODULE_PAGE.match(page.file.src_uri):
        markdown = markdown.replace("](../docs/", "](../../")
    return markdown
