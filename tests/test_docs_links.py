"""The documentation's relative links lead somewhere: every ``[text](path)`` in a tracked Markdown
file names a file or folder of the repository (anchors and web addresses are not checked). A run's
folder that finishes and is renamed, or a record that moves, breaks such links silently otherwise."""
import pathlib
import re
import subprocess

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)\s]*)?\)")


def relative_links(text: str) -> list[str]:
    """The relative link targets of Markdown ``text``, outside code spans and fenced blocks."""
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    text = re.sub(r"`[^`\n]*`", "", text)
    return [m.group(1) for m in LINK.finditer(text) if not re.match(r"[a-z][a-z0-9+.-]*:", m.group(1))]


def test_relative_links_skip_code_anchors_and_addresses():
    text = ("[a](docs/a.md#part) [b](https://x.org/y) `[c](not/a/link)` [d](../d.md)\n"
            "```\n[e](fenced)\n```\n[f](mailto:x@y.org) [g](#local)")
    assert relative_links(text) == ["docs/a.md", "../d.md"]


def test_every_relative_link_in_the_docs_resolves():
    if (ROOT / ".aside").exists():
        pytest.skip("the tree is slimmed for a device call (experiments/slim_tree.sh): docs are aside")
    try:
        files = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True,
                               check=True).stdout.split()
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: the tracked Markdown files are not known")
    assert files, "git lists no Markdown file"
    broken = [f"{md}: {link}" for md in files for link in relative_links((ROOT / md).read_text())
              if not (ROOT / md).parent.joinpath(link).exists()]
    assert not broken, "links to nothing:\n" + "\n".join(broken)
