"""The documentation against the code: the scene parameter table is the generated one, the README stays short and
starts with the two commands, and every relative link and image in README.md and docs/ points to a file."""
import importlib.util
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
README_MAX_BYTES = 10_000
COMMANDS = ('pip install -e . && python -m lab serve\n'
            'pip install -e ".[test]" && python -m pytest -q\n')  # .ci/run runs the second line as it is written here
_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")  # [text](target) and ![alt](target)
_FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.MULTILINE | re.DOTALL)
_CODE_SPAN = re.compile(r"`[^`\n]*`")


def _param_table():
    spec = importlib.util.spec_from_file_location("param_table", REPO / "tools" / "param_table.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_scene_parameter_table_is_the_generated_one():
    tool = _param_table()
    text = tool.DOC.read_text(encoding="utf-8")
    assert tool.table_in(text) == tool.table_markdown(), "run python tools/param_table.py --write"


def test_parameter_table_covers_every_spec_and_reads_units_as_users_do():
    tool = _param_table()
    table = tool.table_markdown()
    for name, specs in tool.spec_tables().items():
        for key in specs:
            assert re.search(rf"`[a-z_.N]*{key}`", table), (name, key)
    assert "°C" in table and "kg/m³" in table and "ml/s" in table and "W/(m² K)" in table
    assert "| C |" not in table and "^2" not in table


def test_readme_is_short_and_starts_with_the_two_commands():
    data = (REPO / "README.md").read_bytes()
    assert len(data) <= README_MAX_BYTES, f"README.md is {len(data)} bytes; move detail to docs/"
    text = data.decode("utf-8")
    first_block = re.search(r"^```[a-z]*\n(.*?)^```", text, re.MULTILINE | re.DOTALL)
    assert first_block is not None and first_block.group(1) == COMMANDS
    assert "\n## " not in text[: first_block.start()], "the two commands come before the first section"


def _markdown_files():
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def _targets(text: str):
    text = _CODE_SPAN.sub("", _FENCE.sub("", text))
    for match in _LINK.finditer(text):
        target = match.group(1)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target) or target.startswith("#"):
            continue  # a URL (http:, mailto:) or an anchor in the same page
        yield target.split("#", 1)[0]


def test_every_relative_link_and_image_points_to_a_file():
    missing = []
    for path in _markdown_files():
        for target in _targets(path.read_text(encoding="utf-8")):
            if not (path.parent / target).exists():
                missing.append(f"{path.relative_to(REPO)}: {target}")
    assert not missing, missing


def test_link_check_finds_links_and_skips_code():
    text = "![a](x.png) [b](docs/y.md#part) [c](https://e.org) [d](#top) `[e](no.md)`\n```\n[f](no2.md)\n```\n"
    assert list(_targets(text)) == ["x.png", "docs/y.md"]
