"""mkdocs hooks for the documentation site (mkdocs.yml: `hooks`).

- **API reference**: one page per public module of `amjax` (every `.py` file whose dotted name has no part starting
  with `_`), each a mkdocstrings `::: amjax.module` block, and the nav's "API reference" section listing them. A module
  added to the package gets its page without anyone editing the docs.
- **Benchmark results**: every file of `benchmarks/results/` is served at the same path in the site, and a link in a
  docs page to `../benchmarks/results/<file>` (the path that works when reading the repository) is pointed at it, so
  `mkdocs build --strict` checks those links too. The tables themselves are included from the same files with
  pymdownx.snippets (`--8<-- "benchmarks/results/<file>"`), never copied by hand.
"""

from __future__ import annotations

import posixpath
import re
from pathlib import Path

from mkdocs.structure.files import File, Files, InclusionLevel

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = "amjax"
RESULTS = "benchmarks/results"
API_SECTION = "API reference"
# The nav's API sections, in the order the data flows (env -> wrapper -> agent -> sweep -> results).
API_GROUPS = ("envs", "wrappers", "agents", "sweep", "analysis")


def public_modules() -> list[str]:
    """Dotted names of amjax's public modules, packages first within each folder."""
    names = []
    for path in sorted((ROOT / PACKAGE).rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[-1] == "__init__":
            parts = parts[:-1]
        if any(part.startswith("_") for part in parts):
            continue
        names.append(".".join(parts))
    return sorted(names, key=lambda name: name.split("."))


def api_page(module: str) -> str:
    return f"api/{module}.md"


def api_nav(modules: list[str]) -> list:
    top = [m for m in modules if m.count(".") <= 1 and m.split(".")[-1] not in API_GROUPS]
    nav: list = [{"Overview": "api/index.md"}, {PACKAGE: [{m: api_page(m)} for m in top]}]
    for group in API_GROUPS:
        prefix = f"{PACKAGE}.{group}"
        members = [m for m in modules if m == prefix or m.startswith(prefix + ".")]
        nav.append({prefix: [{m: api_page(m)} for m in members]})
    listed = {page for section in nav[1:] for entries in section.values() for e in entries for page in e.values()}
    missing = [m for m in modules if api_page(m) not in listed]
    if missing:
        raise ValueError(f"docs/hooks.py: modules with no place in the API nav: {missing}")
    return nav


def on_config(config):
    nav = config["nav"] or []
    for entry in nav:
        if isinstance(entry, dict) and API_SECTION in entry:
            entry[API_SECTION] = api_nav(public_modules())
            return config
    raise ValueError(f"mkdocs.yml: the nav needs an '{API_SECTION}' entry for docs/hooks.py to fill")


def on_files(files: Files, config) -> Files:
    for module in public_modules():
        content = f"::: {module}\n"
        files.append(File.generated(config, api_page(module), content=content))
    for path in sorted((ROOT / RESULTS).rglob("*")):
        if path.is_file():
            name = path.relative_to(ROOT / RESULTS).as_posix()
            files.append(
                File.generated(config, f"{RESULTS}/{name}", abs_src_path=str(path), inclusion=InclusionLevel.NOT_IN_NAV)
            )
    return files


_LINK = re.compile(r"(\]\()([^)\s#]+)")


def on_page_markdown(markdown: str, page, config, files) -> str:
    here = posixpath.dirname(page.file.src_uri)

    def relink(match: re.Match) -> str:
        target = match.group(2)
        if "://" in target or target.startswith(("/", "mailto:")):
            return match.group(0)
        in_repo = posixpath.normpath(posixpath.join("docs", here, target))
        if not in_repo.startswith(RESULTS + "/"):
            return match.group(0)
        return match.group(1) + posixpath.relpath(in_repo, here or ".")

    return _LINK.sub(relink, markdown)
