"""The measured reasons the code, configs and docs cite: every ``experiments/FILE.md, "Section"`` names a file that
exists and a heading in it (a record split or a section renamed must take its citations along)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CITING = ("src/**/*.py", "src/**/*.yaml", "docs/**/*.md", "experiments/**/*.md", "experiments/**/*.py",
          "experiments/**/*.sh", "benchmarks/**/*.py", "README.md")  # fmt: skip
# experiments/PATH.md, then closing backticks, brackets or parentheses, a comma, and (across a line break, a YAML or
# Python comment's "#", or a Markdown link's "(../") the quoted section name
CITATION = re.compile(r'(experiments/[\w./-]+\.md)[`\]\)]*,?(?:[\s#]|\(\.\./)*"([^"]+)"', re.S)


def words(text: str) -> str:
    return re.sub(r"[\s#]+", " ", text).strip()


def citations() -> list[tuple[str, str, str]]:
    """(citing file, cited record, section name) of every citation in the repository."""
    found = []
    for pattern in CITING:
        for path in sorted(ROOT.glob(pattern)):
            for match in CITATION.finditer(path.read_text(encoding="utf-8")):
                found.append((str(path.relative_to(ROOT)), match.group(1), words(match.group(2))))
    return found


def headings(record: Path) -> list[str]:
    return [words(h) for h in re.findall(r"^#+ (.*)$", record.read_text(encoding="utf-8"), re.M)]


def test_the_citation_pattern_reads_a_section_across_a_comment_line_break():
    text = '# measured: experiments/statistics/merges.md, "What a contact\n# looks like".'
    assert [(m.group(1), words(m.group(2))) for m in CITATION.finditer(text)] == [
        ("experiments/statistics/merges.md", "What a contact looks like")
    ]


@pytest.mark.parametrize("citing,record,section", citations())
def test_every_cited_section_is_a_heading_of_its_record(citing, record, section):
    path = ROOT / record
    assert path.is_file(), f"{citing} cites {record}, which does not exist"
    assert any(h.startswith(section) or section in h for h in headings(path)), (
        f'{citing} cites {record}, "{section}": no such heading there'
    )
