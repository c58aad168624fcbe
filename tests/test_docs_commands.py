"""The commands, ids and Python names that README.md and docs/*.md mention outside their code blocks are real.

tests/test_readme.py runs the fenced blocks; the inline code spans of the prose and tables (`...`) are read here,
where a renamed option, id or function would otherwise go stale without a test failing:

- a span that is a command line (`redsim bench envs --steps 8`, or `simulate --escape-saddles` without the `redsim`)
  names a real (sub)command, and each of its options is one of that command's;
- every `RedSim/Name-vN` id of the files, code blocks included, is registered by ``import redsim``;
- every dotted `redsim.a.b` name imports (the longest module, then attributes);
- the keywords of a call span are parameters of the callee: `gym.make("RedSim/...", ...)` (the id's env class,
  followed up its ``**kwargs`` to the base class), a dotted `redsim.a.b(...)`, and the classes of CALLEES; a callee
  that hands ``**kwargs`` on is not checked;
- the keys of `--env-arg KEY=VALUE` / `--setting NAME:KEY=VALUE` (code blocks included) are env arguments, and those
  of ``stepper_options={...}`` are LatentStepper's.

Names the docs mention as tried and removed are listed in GONE, which must match what is found exactly.

The other way round, the code's comments, docstrings and messages cite the docs' sections for their numbers
(`README "Env speed"`, `docs/cubature.md, "Stop 56"`): each quoted part of such a citation begins a heading or a
bold lead (`**Tolerance.** ...`) of that file, so a section moved out of the README cannot leave its citations behind.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import inspect
import re
import shlex
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import gymnasium as gym
import pytest

import redsim  # noqa: F401  # registers the RedSim ids
from redsim.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
if not (ROOT / "README.md").is_file():  # the tests copied beside an installed wheel
    pytest.skip("needs the source checkout (README.md, docs/)", allow_module_level=True)
FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^ *```\w*\n.*?^ *```", re.S | re.M)
SPAN = re.compile(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", re.S)
"""An inline code span: a run of backticks, its text, the same run again."""
OPTION = re.compile(r"-[a-zA-Z]|--[a-z][a-z0-9-]*")
DOTTED = re.compile(r"(?<![\w/.-])redsim(?:\.[A-Za-z_]\w*)+")
ENV_ID = re.compile(r"RedSim/[A-Za-z0-9_]+-v\d+")
CALL = re.compile(r"^((?:[A-Za-z_]\w*\.)*[A-Za-z_]\w*)\((.*)\)$", re.S)
KEYWORD = re.compile(r"(?:^|[,(])\s*([a-z_]\w*)=(?!=)")
ENV_ARG = re.compile(r"""(--env-arg|--setting) +(?:'([^']*)'|"([^"]*)"|([^\s`'"]+))""")
CALLEES = {
    "LatentStepper": "redsim.runtime.LatentStepper",
    "ImplicitEuler": "redsim.integrators.ImplicitEuler",
    "CubatureEnergy": "redsim.cubature.energy.CubatureEnergy",
}
"""Callees the docs name without their module."""
GONE = {
    ("docs/cubature.md", "--share"): "a cubature option tried and reverted (commit 4616374)",
    ("docs/fitting.md", "--modal-radius"): "a fit option tried and reverted (commits e26408a, 2f4eb63)",
    ("docs/env-speed.md", "newton_tail"): "a development stepper option, measured and not kept",
    ("docs/env-speed.md", "legacy_rows"): "a throwaway stepper option of a before/after run",
}
"""Mentions of removed names, each in a sentence that says so: (file, name) -> why."""
SOURCES = [
    path for folder in ("envs", "redsim", "trainers", "examples") for path in sorted((ROOT / folder).rglob("*.py"))
]
"""The code whose comments, docstrings and messages cite README.md's and docs/*.md's sections."""
QUOTED = r"""(?:"[^"\s][^"\n]*"|'[^'\s][^'\n]*')"""
"""A quoted heading: it begins with no space (`" + str(x) + "`, `" "` are the gaps between two string literals)."""
CITATION = re.compile(rf"(README|docs/[\w-]+\.md)\)?(?:,\s*|\s+\(?|\s*\()(?:\" \"|' ')?({QUOTED}(?:,\s*{QUOTED})*)")
"""`README "Section"` or `docs/X.md, "Heading"`, and the quoted parts after one (`README "Cubature", "Stop 56"`); a
message split into two literals before the heading (`"... (README "` / `"'Tolerance')"`) as well."""


def _name(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def _spans(text: str) -> Iterator[tuple[int, str]]:
    """(line, text) of each inline code span outside the fenced blocks; a span over lines (of a quote) as one line."""
    prose = FENCE.sub(lambda block: re.sub(r"[^\n]", " ", block.group(0)), text)
    for span in SPAN.finditer(prose):
        yield prose.count("\n", 0, span.start()) + 1, re.sub(r"\s*\n[\s>]*", " ", span.group(2)).strip()


def _commands() -> dict[tuple[str, ...], argparse.ArgumentParser]:
    """Every (sub)command's parser by its words: () for `redsim`, ("bench", "envs"), ..."""
    found: dict[tuple[str, ...], argparse.ArgumentParser] = {}

    def walk(parser: argparse.ArgumentParser, words: tuple[str, ...]) -> None:
        parser.complete()  # type: ignore[attr-defined]  # redsim.cli.common.Parser: fit's options come on first use
        found[words] = parser
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for word, sub in action.choices.items():
                    walk(sub, (*words, word))

    walk(build_parser(), ())
    return found


def _options(parser: argparse.ArgumentParser) -> set[str]:
    return {option for action in parser._actions for option in action.option_strings}


def _command_problems(span: str, commands: dict[tuple[str, ...], argparse.ArgumentParser]) -> Iterator[str]:
    """What is wrong with a command-line span: an unknown subcommand, or options its command does not take."""
    try:
        words = shlex.split(span)
    except ValueError:  # an unclosed quote cut by the span
        words = span.split()
    words = [word.strip("[]") for word in words[1:] if word not in ("-v", "--verbose")]
    path: tuple[str, ...] = ()
    while words and (*path, words[0]) in commands:
        path = (*path, words.pop(0))
    has_subcommands = any(len(key) == len(path) + 1 and key[: len(path)] == path for key in commands)
    if has_subcommands and words and re.fullmatch(r"[a-z][a-z-]+", words[0]):
        yield f"{words[0]!r}: no subcommand of `{' '.join(('redsim', *path))}`"
        return
    for word in words:
        option = word.split("=")[0]
        if OPTION.fullmatch(option) and option not in _options(commands[path]):
            yield f"{option}: no option of `{' '.join(('redsim', *path))}`"


def _resolve(dotted: str) -> Any:
    """The object a dotted name names: the longest module that imports, then attributes (AttributeError if none)."""
    parts = dotted.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            found: Any = importlib.import_module(".".join(parts[:cut]))
        except ModuleNotFoundError as err:
            module = ".".join(parts[:cut])
            if err.name is not None and (module == err.name or module.startswith(f"{err.name}.")):
                continue  # not a module: an attribute of a shorter one
            raise
        for part in parts[cut:]:
            found = getattr(found, part)
        return found
    raise AttributeError(f"no module in {dotted}")


def _keywords(callee: Any) -> set[str] | None:
    """The keywords a callable takes, a class's up its ``__init__``s' ``**kwargs``; None if it hands on ``**kwargs``."""
    inits = [klass.__init__ for klass in callee.__mro__ if "__init__" in vars(klass)] if inspect.isclass(callee) else []
    names: set[str] = set()
    for function in inits or [callee]:
        parameters = inspect.signature(function).parameters.values()
        names |= {p.name for p in parameters if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)}
        if not any(p.kind == p.VAR_KEYWORD for p in parameters):
            return names - {"self"}
    return None


def _env_keywords(env_id: str) -> set[str] | None:
    keywords = _keywords(_resolve(gym.spec(env_id).entry_point.replace(":", ".")))
    return None if keywords is None else keywords | {"max_episode_steps", "render_mode", "disable_env_checker"}


def _call_problems(span: str) -> Iterator[str]:
    """Keywords of a call span that its callee does not take (gym.make of a RedSim id, redsim.a.b, CALLEES)."""
    call = CALL.match(span)
    if call is None or not KEYWORD.search(call.group(2)):
        return
    callee, arguments = call.groups()
    env_id = re.match(r'\s*"(RedSim/[^"]+)"', arguments)
    if callee == "gym.make" and env_id:
        keywords = _env_keywords(env_id.group(1))
    elif callee.startswith("redsim.") or callee in CALLEES:
        keywords = _keywords(_resolve(CALLEES.get(callee, callee)))
    else:
        return
    for keyword in KEYWORD.findall(arguments):
        if keywords is not None and keyword not in keywords:
            yield f"{keyword}: no keyword of {callee}"


def _option_value_problems(text: str) -> Iterator[tuple[int, str]]:
    """Keys of --env-arg / --setting values that no env takes, and stepper_options keys LatentStepper does not."""
    env_keywords = set().union(*(_env_keywords(i) or set() for i in gym.registry if i.startswith("RedSim/")))
    stepper_keywords = _keywords(_resolve(CALLEES["LatentStepper"])) or set()
    for found in ENV_ARG.finditer(text):
        value = next(group for group in found.groups()[1:] if group is not None)
        if found.group(1) == "--setting":
            value = value.partition(":")[2]
        key = value.partition("=")[0]
        if "=" in value and not key.isupper() and key not in env_keywords:
            yield text.count("\n", 0, found.start()) + 1, f"{key}: no env argument ({found.group(1)})"
    for found in re.finditer(r"stepper_options\s*=\s*\{([^}]*)\}", text):
        for key in re.findall(r'"(\w+)"\s*:', found.group(1)):
            if key not in stepper_keywords:
                yield text.count("\n", 0, found.start()) + 1, f"{key}: no LatentStepper option (stepper_options)"


def problems(text: str, commands: dict[tuple[str, ...], argparse.ArgumentParser]) -> list[tuple[int, str, str]]:
    """(line, name, what is wrong) for every stale mention in a markdown text."""
    found: list[tuple[int, str, str]] = []
    top = {key[0] for key in commands if key}

    def add(line: int, message: str) -> None:
        found.append((line, message.partition(":")[0].strip("'"), message))

    for line, span in _spans(text):
        words = span.split()
        if words and (words[0] == "redsim" or (words[0] in top and OPTION.search(span))):
            command = span if words[0] == "redsim" else f"redsim {span}"
            for message in _command_problems(command, commands):
                add(line, f"{message} in `{span}`")
        for message in _call_problems(span):
            add(line, f"{message} in `{span}`")
    registered = set(gym.registry)
    for match in ENV_ID.finditer(text):
        if match.group(0) not in registered:
            add(text.count("\n", 0, match.start()) + 1, f"{match.group(0)}: not registered by `import redsim`")
    for match in DOTTED.finditer(text):
        try:
            _resolve(match.group(0))
        except (ImportError, AttributeError) as err:
            if isinstance(err, ModuleNotFoundError) and not (err.name or "").startswith("redsim"):
                continue  # an optional dependency this machine lacks: the name itself may be right
            add(text.count("\n", 0, match.start()) + 1, f"{match.group(0)}: {err}")
    for line, message in _option_value_problems(text):
        add(line, message)
    return found


@functools.cache
def _headings(name: str) -> tuple[str, ...]:
    """The headings of a markdown file and the bold leads that open its paragraphs and list items; () if none."""
    path = ROOT / name
    if not path.is_file():
        return ()
    text = path.read_text()
    return (*re.findall(r"^#+\s+(.+)$", text, re.M), *re.findall(r"^(?:[-*]\s+)?\*\*(.+?)\*\*", text, re.M))


def citation_problems(source: str) -> list[str]:
    """The parts of the README and docs citations in Python source that begin no heading or bold lead of their file."""
    flat = re.sub(r"\s*\n\s*(?:#\s*)?", " ", source)  # a citation wraps over docstring and comment lines
    stale = []
    for found in CITATION.finditer(flat):
        headings = _headings("README.md" if found.group(1) == "README" else found.group(1))
        for part in re.findall(QUOTED, found.group(2)):
            if not any(heading.startswith(part[1:-1]) for heading in headings):
                stale.append(f"{found.group(1)} {part}")
    return stale


@pytest.fixture(scope="module")
def commands() -> dict[tuple[str, ...], argparse.ArgumentParser]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return _commands()


def test_inline_mentions_name_real_commands_options_ids_and_names(
    commands: dict[tuple[str, ...], argparse.ArgumentParser],
) -> None:
    stale, gone = [], set()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the out-of-date ids' deprecation warnings on import
        for path in FILES:
            for line, name, message in problems(path.read_text(), commands):
                if (_name(path), name) in GONE:
                    gone.add((_name(path), name))
                else:
                    stale.append(f"{_name(path)}:{line}: {message}")
    assert not stale, "stale mentions (rename them, or list a removed name in GONE):\n" + "\n".join(stale)
    assert gone == set(GONE), f"GONE lists mentions no longer found: {set(GONE) - gone}"


@pytest.mark.parametrize(
    ("text", "name"),
    [
        ("run `redsim bench envs --steps 8 --no-such-option 2`", "--no-such-option"),
        ("run `simulate --escape-all` then", "--escape-all"),
        ("`redsim bench nothing`", "nothing"),
        ("`redsim fit\n> chain --step 10`", "--step"),
        ("the id RedSim/Chain-v9 in prose", "RedSim/Chain-v9"),
        ("`redsim.envs.make_vector`", "redsim.envs.make_vector"),
        ("`redsim.no_module.thing` too", "redsim.no_module.thing"),
        ('`gym.make("RedSim/Chain-v0", time_step=0.005)`', "time_step"),
        ("`LatentStepper(..., warmstart=False)`", "warmstart"),
        ("`redsim.integrators.ImplicitEuler(space, dt, retry=None)`", "retry"),
        ("```bash\nredsim bench env-ab ID --setting 'a:stepper_options={\"tols\":1e-5}'\n```", "tols"),
        ("--env-arg dtt=0.01", "dtt"),
    ],
)
def test_a_stale_mention_is_found(
    text: str, name: str, commands: dict[tuple[str, ...], argparse.ArgumentParser]
) -> None:
    """Each check finds the stale name it is for (the real files pass only if the checks look)."""
    assert name in [found for _, found, _ in problems(text, commands)]


@pytest.mark.parametrize(
    "text",
    [
        "`redsim bench envs --envs RedSim/Chain-v0 --steps 8 --budget 8` and `redsim -v bench envs ...`",
        "`redsim train-agent RedSim/MiniChain-v0 [--her] --steps N`, `simulate --escape-saddles`",
        '`gym.make("RedSim/MiniChain-v0", scene_params={"density": 8000.0}, fit_if_missing=True)`',
        '`LatentStepper(..., warm_start=False)`, `redsim.envs.make(..., task="reach")` (**kwargs handed on)',
        "--env-arg cubature=true --env-arg KEY=VALUE --setting 'b:stepper_options={\"tol\": 1e-5}'",
        "```bash\nredsim bench envs --no-such-option\n```",  # a block's command: tests/test_readme.py parses it
    ],
)
def test_a_real_mention_passes(text: str, commands: dict[tuple[str, ...], argparse.ArgumentParser]) -> None:
    assert problems(text, commands) == []


def test_the_code_s_citations_name_sections_the_docs_have() -> None:
    assert len(SOURCES) > 100
    stale = [f"{_name(path)}: {part}" for path in SOURCES for part in citation_problems(path.read_text())]
    assert not stale, "citations of no heading or bold lead (point them where the text went):\n" + "\n".join(stale)


def test_the_docs_citations_and_the_readme_s_links_name_sections_that_exist() -> None:
    """README.md's and docs/*.md's own citations (`docs/envs.md, "Heading"`, `README "Section"`) each begin a heading
    or bold lead of their file, and every in-page link of the README (`](#anchor)`) is a heading's anchor (GitHub's:
    lower case, punctuation but - and _ dropped, spaces as -). A review (helper-256) found one that pointed at nothing
    after the README's shortening (stop 71)."""
    stale = [f"{_name(path)}: {part}" for path in FILES for part in citation_problems(FENCE.sub("", path.read_text()))]
    assert not stale, "citations of no heading or bold lead:\n" + "\n".join(stale)
    readme = FENCE.sub("", (ROOT / "README.md").read_text())
    anchors = {
        re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in re.findall(r"^#+\s+(.+)$", readme, re.M)
    }
    links = re.findall(r"\]\(#([^)]+)\)", readme)
    assert len(links) > 10 and sorted(set(links) - anchors) == []


@pytest.mark.parametrize(
    ("source", "stale"),
    [
        ('# 1.01x (README "Cubature", "Stop 56")', ['README "Stop 56"']),
        ('"""Measured (README "No such section")."""', ['README "No such section"']),
        (
            '"""One pass (docs/env-speed.md, "Stop 28\'s\n    lost heading")."""',
            ['docs/env-speed.md "Stop 28\'s lost heading"'],
        ),
        ("warn(\"use a longer dt (README 'Tolerances of old')\")", ["README 'Tolerances of old'"]),
        ('# (docs/nothing.md "Stop 1")', ['docs/nothing.md "Stop 1"']),
        ('in [docs/runtime.md](docs/runtime.md), "No such part")', ['docs/runtime.md "No such part"']),  # markdown
        ('# (README "Latent runtime", "Tolerance"; docs/env-speed.md, "Stop 28\'s\n# measurements")', []),
        ("warn(\"use dtype='float64' or a longer dt (README 'Tolerance')\")", []),
        ('"""The README\'s subspace table, and docs/agents.md (the whole file)."""', []),
        # two string literals, not a citation; and a citation split over two literals (implicit concatenation)
        ('log("see the README " + str(x) + " and docs/envs.md " + "x")', []),
        ('raise ValueError(\n    "use a longer dt (README "\n    "\'Tolerance\')"\n)', []),
        ('raise ValueError("(README "\n    "\'Tolerances of old\')")', ["README 'Tolerances of old'"]),
    ],
)
def test_a_citation_is_checked_against_its_file_s_headings(source: str, stale: list[str]) -> None:
    """Each quoted part of a citation, over a line break too; a heading's prefix passes (`"Stop 28's measurements"`)."""
    assert citation_problems(source) == stale
