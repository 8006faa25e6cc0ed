"""The manual builds, its generated references cover the code, and nothing in it goes stale.

``mkdocs build --strict`` fails on a broken link, a page missing from the nav or a nav
entry without its page; the configuration and CLI references are generated from
``gateway/config.py`` and ``gateway/cli/main.py`` by ``docs/hooks/reference.py``.
"""

from __future__ import annotations

import html
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import click
import pytest
import yaml
from pydantic import BaseModel

from gateway.cli.main import main as cli_main
from gateway.config import GatewayConfig
from gateway.config_schema import config_schema_text

ROOT = Path(__file__).resolve().parents[1]
SCHEMA_FILE = ROOT / "docs" / "config.schema.json"
REGENERATE = ".venv/bin/python -m gateway.config_schema > docs/config.schema.json"


def build(config: Path, out: Path) -> subprocess.CompletedProcess[str]:
    """``mkdocs build --strict`` of ``config`` into ``out``, at its normal log level: with
    ``--quiet`` mkdocs drops its warnings before strict mode counts them, and a page
    missing from the nav passed."""
    return subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The manual built once into a temporary folder, strict, without a single warning."""
    out = tmp_path_factory.mktemp("site")
    done = build(ROOT / "mkdocs.yml", out)
    log = done.stdout + done.stderr
    assert done.returncode == 0, f"mkdocs build --strict failed:\n{log}"
    assert "WARNING" not in log, f"mkdocs build warned:\n{log}"
    return out


def test_a_page_left_out_of_the_nav_fails_the_build(tmp_path: Path) -> None:
    """The same build with the console page's nav entry removed is refused, naming it."""
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))
    config["docs_dir"] = str(ROOT / "docs")
    config["hooks"] = [str(ROOT / hook) for hook in config["hooks"]]
    config["nav"] = without_page(config["nav"], "console.md")
    assert config["nav"] != yaml.safe_load((ROOT / "mkdocs.yml").read_text())["nav"]
    trimmed = tmp_path / "mkdocs.yml"
    trimmed.write_text(yaml.safe_dump(config), encoding="utf-8")
    done = build(trimmed, tmp_path / "site")
    log = done.stdout + done.stderr
    assert done.returncode != 0, log
    assert 'not included in the "nav"' in log and "console.md" in log, log


def without_page(nav: Any, page: str) -> Any:
    """``nav`` with every entry pointing at ``page`` removed."""
    if isinstance(nav, list):
        return [without_page(entry, page) for entry in nav if not points_at(entry, page)]
    if isinstance(nav, dict):
        return {title: without_page(entry, page) for title, entry in nav.items()}
    return nav


def points_at(entry: Any, page: str) -> bool:
    return entry == page or (isinstance(entry, dict) and list(entry.values()) == [page])


def page_text(site: Path, name: str) -> str:
    """The page's HTML with tags dropped and entities decoded."""
    return html.unescape(re.sub(r"<[^>]+>", "", (site / name).read_text(encoding="utf-8")))


def models_with_paths() -> list[tuple[str, type[BaseModel]]]:
    """Every section reachable from the top level, with a path as the reference writes it."""
    sys.path.insert(0, str(ROOT / "docs" / "hooks"))
    try:
        from reference import holds_list, nested_models
    finally:
        sys.path.pop(0)
    found: list[tuple[str, type[BaseModel]]] = []
    todo: list[tuple[str, type[BaseModel]]] = [("", GatewayConfig)]
    while todo:
        path, model = todo.pop()
        if any(path == p for p, _ in found):
            continue
        found.append((path, model))
        for name, field in model.model_fields.items():
            suffix = "[]" if holds_list(field.annotation) else ""
            for child in nested_models(field.annotation):
                todo.append((f"{path}.{field.alias or name}{suffix}".lstrip("."), child))
    return found


def test_configuration_reference_lists_every_section_and_key(site: Path) -> None:
    text = page_text(site, "configuration.html")
    sections = models_with_paths()
    assert len(sections) > 20  # machines, cnc, compensation, logging, scada, … and their parts
    for path, model in sections:
        if path:
            assert f"\n{path}\n" in text, f"section {path} missing from the configuration page"
        for name, field in model.model_fields.items():
            assert (field.alias or name) in text, f"{path}.{name} missing"
    assert "clamp_um" in text and "50.0" in text  # a key with its default
    for directive in ("type: ignore", "noqa", "pragma"):  # comments for tools, not readers
        assert directive not in text, f"{directive!r} in the configuration reference"
    assert "the login name" in text  # web.users[].username's own words instead


def test_cli_reference_lists_every_command_and_option(site: Path) -> None:
    text = page_text(site, "cli.html")

    def walk(cmd: click.Command, path: str) -> None:
        assert f"Usage: {path}" in text, f"{path} missing from the CLI page"
        for param in cmd.params:
            for opt in getattr(param, "opts", []):
                if opt.startswith("--"):
                    assert opt in text, f"{path} {opt} missing"
        if isinstance(cmd, click.Group):
            for name, sub in cmd.commands.items():
                walk(sub, f"{path} {name}")

    walk(cli_main, "python -m gateway")
    assert "python -m gateway models promote" in text


def test_edge_box_page_is_the_deploy_readme(site: Path) -> None:
    first_heading = (ROOT / "deploy" / "README.md").read_text(encoding="utf-8").splitlines()[0]
    assert first_heading.lstrip("# ") in page_text(site, "deployment/edge-box.html")


def test_committed_config_schema_is_current() -> None:
    committed = SCHEMA_FILE.read_text(encoding="utf-8")
    assert committed == config_schema_text(), f"docs/config.schema.json is stale: {REGENERATE}"


def test_config_schema_command_prints_the_schema() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "gateway.config_schema"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == config_schema_text()
    assert '"machines"' in done.stdout and '"additionalProperties": false' in done.stdout


def test_readme_links_point_at_files() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", readme)
    local = [link for link in links if "://" not in link]
    assert local, "the README links into the manual"
    missing = [link for link in local if not (ROOT / link).exists()]
    assert not missing, f"README links to missing files: {missing}"
