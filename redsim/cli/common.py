"""What every ``redsim`` command shares: errors, output, input parsing, scene arguments, threads.

Bad input is a :class:`CliError`, reported by :func:`redsim.cli.main` as one
``redsim: error: ...`` line on stderr with its exit status.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import redsim
from redsim.interrupts import deferred_interrupts

if TYPE_CHECKING:
    from redsim.scene import Scene

EXIT_OK = 0
EXIT_SCENE_FAILED = 1
EXIT_USAGE = 2
EXIT_NAN = 3
EXIT_FAILED_STEP = 4
EXIT_INTERRUPTED = 130


class CliError(Exception):
    """Bad command-line input: reported as one line on stderr with exit status ``code``."""

    def __init__(self, message: str, code: int = EXIT_USAGE) -> None:
        super().__init__(message)
        self.code = code


def check_device_option(device: str) -> None:
    """``--device`` refused as a CLI error where redsim cannot run on it (:func:`redsim.devices.check_device`)."""
    from redsim.devices import check_device

    try:
        check_device(device)
    except ValueError as err:
        raise CliError(f"--device: {err}") from None


class SceneNotRebuilt(CliError):
    """A checkpoint whose scene cannot be rebuilt from its ``.json`` (an in-memory mesh, a moved mesh file, ...)."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose usage errors become :class:`CliError` (one line, exit status 2), and whose arguments
    may be added on first use (:meth:`add_later`)."""

    _pending: Callable[[Parser], None] | None = None

    def error(self, message: str) -> NoReturn:
        raise CliError(f"{message} (see `{self.prog} --help`)")

    def add_later(self, add: Callable[[Parser], None]) -> None:
        """Add this parser's arguments with ``add(self)`` when it first parses or prints its help, not now: a command
        whose help text needs a module that imports torch (``fit``'s defaults) leaves ``redsim --help`` quick."""
        self._pending = add

    def complete(self) -> Parser:
        """This parser with every argument added (:meth:`add_later`)."""
        if self._pending is not None:
            add, self._pending = self._pending, None
            with deferred_interrupts(forced=False):  # the options' module loads torch (parser._load_torch)
                add(self)
        return self

    def format_usage(self) -> str:
        self.complete()
        return super().format_usage()

    def format_help(self) -> str:
        self.complete()
        return super().format_help()

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        """As argparse's, recording in ``_prog`` the innermost (sub)command that parsed (it returns first)."""
        self.complete()
        namespace, extras = super().parse_known_args(args, namespace)
        if not hasattr(namespace, "_prog"):
            namespace._prog = self.prog
        return namespace, extras

    def parse_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> argparse.Namespace:
        """As argparse's, but arguments left over point to the subcommand's ``--help``, not the top-level one."""
        namespace, extras = self.parse_known_args(args, namespace)
        if extras:
            raise CliError(f"unrecognized arguments: {' '.join(extras)} (see `{namespace._prog} --help`)")
        return namespace


# -- output ---------------------------------------------------------------------------------
class StdoutClosed(Exception):
    """stdout's reader went away (``redsim ... | head``): :func:`redsim.cli.main` exits quietly."""


def out(text: str = "") -> None:
    try:
        print(text, flush=True)
    except BrokenPipeError:
        raise StdoutClosed from None


def _finite_or_none(obj: Any) -> Any:
    """``obj`` with NaN and inf floats replaced by None, so the output is strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite_or_none(v) for v in obj]
    return obj


def json_out(obj: Any) -> None:
    out(json.dumps(_finite_or_none(obj), indent=2, default=str, allow_nan=False))


def warn(text: str) -> None:
    say(f"redsim: warning: {text}")


def say(text: str) -> None:
    """Print ``text`` on stderr; nothing where there is none (``2>&-``: Python sets ``sys.stderr`` to None, and
    ``print(file=None)`` would write into stdout, the command's result)."""
    if sys.stderr is not None:
        print(text, file=sys.stderr, flush=True)


_COLOUR = re.compile(r"\x1b\[[0-9;]*m")
"""A terminal colour code (Gymnasium's ``logger.warn`` colours its messages yellow)."""
_RELAYS = ("warnings", "_py_warnings", "gymnasium.logger")
"""Modules that issue a warning on behalf of their caller: the caller is its source (``gym.logger.warn`` called
by redsim's envs says redsim's message)."""


def show_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: Any = None,
    line: str | None = None,
    *,
    said: set[str] | None = None,
) -> None:
    """:func:`warnings.showwarning` of the command line (:func:`redsim.cli.main`): a Python warning as one
    ``redsim: warning: MESSAGE`` line on stderr, without the file, line number and source line of the ``warn`` call.

    Python's filters run before this (``-W error`` still raises, ``-W ignore`` still silences, ``default`` still
    shows each location once). The parenthesis names what the user needs to tell the warning apart: the package
    whose code issued it, where that is not redsim (a torch, Gymnasium or SB3 warning is about their API or
    defaults, not a redsim setting), and its category, except for redsim's own UserWarnings (what ``-W
    ignore::CATEGORY`` filters): ``redsim: warning (stable_baselines3, UserWarning): ...``, ``redsim: warning
    (RuntimeWarning): ...``. A message's further lines are indented under its first; colour codes are dropped.

    ``said``: the lines said so far in this run (:func:`redsim.cli.main` gives each run its own set). A line in it is
    not said again, unless an ``always`` filter (``-W always``) could match the warning. Python's own once-per-location
    memory is not enough: every ``warnings.catch_warnings`` or filter change anywhere in the process (the standard
    library's ``subprocess``, Gymnasium, ours) resets it, and ``redsim bench envs`` said an env's warning once per env
    it built.
    """
    text = _COLOUR.sub("", str(message)).strip().removeprefix("WARN: ")  # Gymnasium's logger: "WARN: " in colour
    frame = sys._getframe(1)  # the warnings module's _showwarnmsg, then the code that called warnings.warn
    while frame is not None and frame.f_globals.get("__name__") in _RELAYS:
        frame = frame.f_back
    module = Path(filename).stem if frame is None else str(frame.f_globals.get("__name__", Path(filename).stem))
    package = module.partition(".")[0]
    tags = [] if package == "redsim" else [package]
    tags += [] if package == "redsim" and category is UserWarning else [category.__name__]
    head = "redsim: warning" + (f" ({', '.join(tags)})" if tags else "")
    first, *more = text.splitlines() or [""]
    shown = "\n".join([f"{head}: {first}", *(f"  {each}" if each else "" for each in more)])
    if said is not None:
        if shown in said and not _always_shown(str(message), category):
            return
        said.add(shown)
    file = file or sys.stderr
    if file is None:  # no stderr (`2>&-`): print(file=None) would write into stdout; Python's display drops it
        return
    try:
        print(shown, file=file, flush=True)
    except OSError:  # stderr went away: as Python's own display, the warning is lost, not the command
        pass


def _always_shown(text: str, category: type[Warning]) -> bool:
    """Whether an ``always`` filter matches the warning's message and category (its module and line not checked: a
    repeat that may have been asked for is said)."""
    return any(
        action == "always" and (message is None or message.match(text)) and issubclass(category, kind)
        for action, message, kind, _, _ in warnings.filters
    )


def warn_earlier_frames(folder: str | Path, flag: str) -> None:
    """Say on stderr that ``folder`` (given as ``flag``) holds mesh frames from an earlier run: they are not removed,
    and this run's frames replace only those of the same number."""
    from redsim.render import frames_in

    if earlier := frames_in(folder):
        warn(
            f"{flag} {shown_path(folder)} already holds {len(earlier)} mesh files (frame_*.ply) from an earlier run; "
            "they stay, and this run replaces only the frames it writes (use an empty folder to keep runs apart)"
        )


def note(text: str) -> None:
    """A progress line on stderr (stdout stays the command's result)."""
    say(text)


def error(text: str) -> None:
    say(f"redsim: error: {text}")


def file_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def shown_path(path: str | Path) -> str:
    """``path`` as a report prints it: inside the installed package as ``redsim/...`` (the same on every
    machine), else relative to the working folder where it lies below it, else as given."""
    path = Path(path)
    resolved = path.resolve()
    package = Path(redsim.__file__).resolve().parent
    for base, prefix in ((package, Path("redsim")), (Path.cwd().resolve(), Path())):
        if resolved.is_relative_to(base):
            return str(prefix / resolved.relative_to(base))
    return str(path)


# -- input ----------------------------------------------------------------------------------
def catalog_names() -> list[str]:
    return list(redsim.scenes.names())


def check_scene_name(name: str, *, takes_files: bool = True) -> None:
    """Refuse a name that is not a catalog scene; a file path given for one is told where files go (``takes_files``:
    the command has ``--mesh`` and ``--spec``; else it runs on catalog scenes only)."""
    names = catalog_names()
    if name not in names:
        hint = ""
        if redsim.scenes.looks_like_an_env_id(name):
            hint = " (an env id: demo, train-agent, eval-agent and bench envs take ids; this command takes a scene)"
        elif redsim.scenes.looks_like_a_path(name):
            hint = (
                " (a file path: a mesh goes with --mesh PATH --kind fem|tets|cloth, a spec or checkpoint .json with "
                "--spec)"
                if takes_files
                else " (a file path: this command runs on catalog scenes only)"
            )
        raise CliError(f"unknown scene {name!r}{hint}; valid scenes: {', '.join(names)}")


def parse_env_id(text: str) -> str:
    """The RedSim id ``text`` names, bare or with Gymnasium's module prefix (``redsim:RedSim/MiniChain-v0``:
    ``gym.make`` imports the module before the colon; here it must be redsim or one of its modules, already imported).

    Raises:
        CliError: not a RedSim id, naming the valid ones.
    """
    module, sep, name = text.partition(":")
    bare = name if sep and (module == "redsim" or module.startswith("redsim.")) else text
    if bare not in redsim.envs.ids():
        meant = [i for i in redsim.envs.ids() if i.lower() == f"redsim/{bare}".lower()]  # MiniChain-v0, minichain-v0
        hint = f" (did you mean {meant[0]}? ids start with RedSim/)" if meant else ""
        raise CliError(
            f"unknown env {text!r}{hint}; valid: {', '.join(redsim.envs.ids())} (each may take the prefix redsim:)"
        )
    return bare


def warn_if_out_of_date(env_id: str) -> None:
    """Say on stderr, in one line, that ``env_id`` (a RedSim id) has a later version; Gymnasium's own multi-line
    warning of it is silenced in the CLI (:func:`redsim.cli.parser.main`). Benches, which time older versions on
    purpose, do not call this."""
    name, version = env_id.rsplit("-v", 1)
    latest = max(int(other.rsplit("-v", 1)[1]) for other in redsim.envs.ids() if other.rsplit("-v", 1)[0] == name)
    if int(version) < latest:
        warn(f'{env_id} is out of date: {name}-v{latest} is its latest version (README "Gymnasium environments")')


def build_scene(name: str, params: dict[str, Any] | None = None) -> Scene:
    """Build catalog scene ``name``; unknown names and rejected parameters become CliErrors."""
    check_scene_name(name)
    params = params or {}
    try:
        return redsim.scenes.build(name, **params)
    except (TypeError, ValueError, KeyError) as err:
        shown = ", ".join(f"{k}={json.dumps(v)}" for k, v in params.items()) or "no parameters"
        message = str(err.args[0]) if isinstance(err, KeyError) and err.args else str(err)
        raise CliError(f"cannot build scene {name!r} with {shown}: {message}") from err


def parse_params(items: Sequence[str], flag: str = "--param", example: str = "links=3") -> dict[str, Any]:
    """``KEY=VALUE`` pairs (given with ``flag``) with VALUE a JSON literal (``3``, ``0.5``, ``false``, ``"text"``);
    a KEY given twice is an error (the second would silently win)."""
    params: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key.isidentifier():
            raise CliError(f"malformed {flag} {item!r}: expected KEY=VALUE, e.g. {flag} {example}")
        if key in params:
            raise CliError(f"{flag} {key} given twice; give each KEY once")
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError as err:
            raise CliError(
                f"bad {flag} {item!r}: VALUE must be a JSON literal such as 3, 0.5, false, [1, 2] "
                f"or '\"text\"' (quotes included)"
            ) from err
    return params


NOT_ENV_ARGS = {
    "disable_env_checker": "gym.make's own option, not the env's (the command makes vector envs, which do not take it)",
    "render_mode": "the command sets the render mode itself",
}
"""``gym.make`` keywords that :func:`parse_env_args` refuses, and why."""

PATH_ENV_ARGS = ("subspace", "cubature")
"""The env keywords that take a path (a checkpoint); :func:`parse_env_args` reads a leading ``~`` in them, as
:func:`expand_home` does in the command's own path options."""


def parse_env_args(
    items: Sequence[str], env_ids: Sequence[str], flag: str = "--env-arg", example: str = "cubature=true"
) -> dict[str, Any]:
    """Env keyword arguments from ``KEY=VALUE`` pairs (VALUE a JSON literal; given with ``flag``), checked by making
    each of ``env_ids`` once with them, so that a bad one is a one-line :class:`CliError` rather than a traceback.
    ``gym.make``'s own ``disable_env_checker`` (the commands make vector envs, which pass every key to the env) and
    ``render_mode`` (the command picks it) are refused. A path (:data:`PATH_ENV_ARGS`) that starts with ``~`` is read
    as the shell reads one (the quotes JSON needs, ``subspace='"~/runs/x.pt"'``, keep the shell from it; the env takes
    it as typed, as ``open`` does)."""
    kwargs = parse_params(items, flag, example)
    for key, why in NOT_ENV_ARGS.items():
        if key in kwargs:
            raise CliError(f"{flag} {key}: {why}; drop it")
    for key in PATH_ENV_ARGS:
        if isinstance(kwargs.get(key), str) and kwargs[key].startswith("~"):
            kwargs[key] = os.path.expanduser(kwargs[key])
    if kwargs:
        import gymnasium as gym

        for env_id in env_ids:
            try:
                gym.make(env_id, **kwargs).close()
            except (TypeError, ValueError) as err:
                raise CliError(f"cannot make {env_id} with {flag} {' '.join(items)}: {err}") from err
    return kwargs


def parse_loads(items: Sequence[str], scene: Scene) -> dict[str, list[float]] | None:
    """``HANDLE=FX,FY[,FZ]`` forces [N] on the scene's handles; None when there are none."""
    if not items:
        return None
    example = "HANDLE=FX,FY" + (",FZ" if scene.dim == 3 else "")
    loads: dict[str, list[float]] = {}
    for item in items:
        handle, sep, value = item.partition("=")
        handle = handle.strip()
        try:
            force = [float(c) for c in value.split(",")] if sep and handle else None
        except ValueError:
            force = None
        if force is None or not all(math.isfinite(f) for f in force):
            raise CliError(f"malformed --load {item!r}: expected {example} with finite numbers")
        if handle not in scene.handle_names:
            valid = ", ".join(scene.handle_names) if scene.handles else "none (this scene has no handles)"
            raise CliError(f"unknown handle {handle!r} in --load for scene {scene.name!r}; valid handles: {valid}")
        if len(force) != scene.dim:
            raise CliError(
                f"--load {item!r} has {len(force)} component(s), but scene {scene.name!r} is {scene.dim}D: "
                f"expected {example}"
            )
        if handle in loads:
            raise CliError(f"--load gives handle {handle!r} twice")
        loads[handle] = force
    return loads


def check_writable(path: str, flag: str, *, folder: bool) -> None:
    """Raise CliError unless ``path`` (given as ``flag``; a folder to write into where ``folder``, else a file) could
    be made and written. Nothing is left behind: the nearest existing folder above it must be a folder that a file
    can be made in (tried, not asked of ``os.access``, which says yes to root everywhere and to anyone on ``/proc``)."""
    if folder and Path(path).exists() and not Path(path).is_dir():
        raise CliError(f"cannot write into {flag} {path}: it is a file, not a folder")
    above = Path(path).absolute().parent
    while not above.exists() and above != above.parent:
        above = above.parent
    if not above.is_dir():
        raise CliError(f"cannot write {flag} {path}: {above} is a file, not a folder")
    if (why := write_error(above)) is not None:
        raise CliError(f"cannot write {flag} {path}: no file can be made in {above} ({why})")


def write_error(folder: Path) -> str | None:
    """Why no file can be made in the existing ``folder`` (tried: ``os.access`` says yes to root everywhere and to
    anyone on ``/proc``); None where one can. Nothing is left behind."""
    try:
        with tempfile.TemporaryFile(dir=folder):
            return None
    except OSError as err:
        return err.strerror or str(err)


PATH_ARGS = ("out", "meshes", "spec", "mesh", "checkpoint", "checkpoints", "baseline", "cubature", "model", "scene")
"""The arguments (by ``dest``) that name a file or folder; :func:`expand_home` reads a leading ``~`` in them."""


def expand_home(args: argparse.Namespace) -> None:
    """Read a leading ``~`` or ``~user`` in the path arguments (:data:`PATH_ARGS`) as the shell does: the shell leaves
    ``--out=~/runs`` and a quoted ``'~/runs'`` as typed, and the command made a folder named ``~`` in the working
    folder. A name that does not start with ``~`` (a scene, an env id, ``shipped``) is left as it is."""
    for dest in PATH_ARGS:
        value = getattr(args, dest, None)
        if isinstance(value, str) and value.startswith("~"):
            setattr(args, dest, os.path.expanduser(value))


def parse_list(text: str, what: str, item: Callable[[str], Any] | None = None) -> list[Any]:
    """The items of a comma-separated list (``what`` names the option in the error), each as ``item`` reads it
    (default: the text); an item given twice is an error (a bench would run it twice), also where two spellings
    read the same (``redsim:RedSim/X-v0`` and ``RedSim/X-v0``, ``1`` and ``01``)."""
    items = [s.strip() for s in text.split(",") if s.strip()]
    if not items:
        raise CliError(f"{what} must be a comma-separated list, got {text!r}")
    values = items if item is None else [item(s) for s in items]
    repeated = next((i for i, value in enumerate(values) if value in values[:i]), None)
    if repeated is not None:
        first, again = items[values.index(values[repeated])], items[repeated]
        given = f"{first!r} twice" if first == again else f"{first!r} and {again!r}, which read the same,"
        raise CliError(f"{what} gives {given}; give each once")
    return values


# -- shared options -------------------------------------------------------------------------
def machine_line(machine: dict[str, Any], device: str) -> str:
    """One line on the machine a benchmark ran on (from :func:`redsim.bench.machine_info`): the CPU with its family
    and model, cores, load, torch with the vector kernels it runs, threads and device."""
    load = machine["load_average_1min"]
    cpu = machine["processor"]
    extra = [a for a in (machine["machine"], machine["cpu_family_model"]) if a and a != cpu]
    cpu = f"{cpu} ({', '.join(extra)})" if extra else cpu
    kernels = f" ({machine['cpu_capability']} kernels)" if machine["cpu_capability"] else ""
    return (
        f"machine: {cpu}, {machine['cpu_count']} CPUs"
        + (f" (load {load:.2f})" if load is not None else "")
        + f", torch {machine['torch']}{kernels}, {machine['torch_threads']} threads, device {device}"
        + (f" ({machine['cuda_device']})" if device.startswith("cuda") else "")
    )


def parse_ints(text: str, what: str) -> list[int]:
    """Comma-separated integers >= 1 (``what`` names the option in the error)."""
    try:
        values = parse_list(text, what, int)
    except ValueError as err:
        raise CliError(f"{what} must be comma-separated integers, got {text!r}") from err
    if min(values) < 1:
        raise CliError(f"{what} must be >= 1, got {text!r}")
    return values


def seconds(text: str) -> float:
    """argparse type of a time budget: a finite number of seconds > 0."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"must be a number of seconds > 0, got {text!r}")
    return value


def non_negative_seed(text: str, bits: int = 64) -> int:
    """argparse type of a seed: an integer in [0, 2**bits - 1] (64: Gymnasium's and NumPy's seeding take it, and
    torch's generators, which overflowed past it; :func:`sb3_seed`: 32)."""
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value < 2**bits:
        raise argparse.ArgumentTypeError(f"must be an integer in [0, 2**{bits} - 1], got {text!r}")
    return value


def sb3_seed(text: str) -> int:
    """argparse type of a stable-baselines3 algorithm's seed: an integer in [0, 2**32 - 1] (SB3 seeds NumPy's
    legacy generator, which refuses more)."""
    return non_negative_seed(text, 32)


def add_threads(parser: argparse.ArgumentParser, default: int | None = None) -> None:
    """``--threads N``: torch's intra-op threads for the command."""
    shown = "torch's default: all cores" if default is None else str(default)
    parser.add_argument(
        "--threads", type=int, default=default, metavar="N", help=f"torch intra-op threads (default {shown})"
    )


def add_out_folder(parser: argparse.ArgumentParser, help: str, default: str | None = None) -> None:
    """``--out DIR``, a folder the command writes into (made if missing; an existing file there is refused up front)."""
    parser.add_argument("--out", default=default, metavar="DIR", help=help)
    parser.set_defaults(out_is_folder=True)


def finish_command(
    parser: argparse.ArgumentParser,
    func: Any,
    json_help: str,
    *,
    threads: bool = True,
    default_threads: int | None = None,
) -> None:
    """End a command's options: ``--threads`` (commands that compute), ``--json``, and the function it runs."""
    if threads:
        add_threads(parser, default_threads)
    parser.add_argument("--json", action="store_true", help=json_help)
    parser.set_defaults(func=func)


@contextlib.contextmanager
def command_threads(args: argparse.Namespace) -> Iterator[None]:
    """Run the command on ``--threads`` torch intra-op threads, giving an in-process caller (a test, a notebook) its
    own setting back after it; nothing (and no torch import) when the command has no ``--threads`` or it is unset."""
    threads = getattr(args, "threads", None)
    if threads is None:
        yield
        return
    from redsim.threads import MAX_THREADS, check_threads, torch_threads

    try:
        threads = check_threads(threads)
    except ValueError as err:  # 99999999999 was an OverflowError traceback, 40000 a segfault
        raise CliError(f"--threads must be an integer in [1, {MAX_THREADS}], got {threads}") from err
    with torch_threads(threads):
        yield


# -- scene arguments ------------------------------------------------------------------------
def add_scene_args(parser: argparse.ArgumentParser) -> None:
    """A catalog scene name, ``--mesh PATH --kind fem|tets|cloth`` or ``--spec FILE``; builder params with
    ``--param``."""
    parser.add_argument(
        "scene", nargs="?", help="catalog name (see `redsim scenes --all`); or give --mesh or --spec instead"
    )
    parser.add_argument(
        "--spec",
        metavar="FILE",
        help='a scene spec JSON, {"scene": NAME, "scene_params": {...}}; a checkpoint\'s .json is one',
    )
    _add_mesh_args(parser)


def _add_mesh_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--mesh", metavar="PATH", help="build the scene from your own mesh file (needs --kind)")
    parser.add_argument(
        "--kind",
        choices=("fem", "tets", "cloth"),
        help="builder for --mesh: fem (a watertight surface mesh, voxelized into a neo-Hookean solid), tets (a "
        "tetrahedral mesh as a .npz of 'vertices' and 'tets', a neo-Hookean solid as given) or cloth (a surface's "
        "triangles as cloth); its arguments come with --param (e.g. young=2e5, pin='\"min_y\"', voxel_pitch=0.05, "
        "name='\"bunny\"')",
    )
    parser.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="scene build parameter, VALUE a JSON literal (e.g. links=3, gravity=false); repeatable (in a bench, "
        "with --mesh only: --scenes are built with their defaults)",
    )


def scene_from_args(args: argparse.Namespace) -> Scene:
    """The scene named by ``args.scene`` or built from ``args.mesh`` with ``args.kind`` (see :func:`add_scene_args`)."""
    from redsim.scenes.spec import mesh_scene

    params = parse_params(args.param)
    spec = getattr(args, "spec", None)
    given = [
        what
        for what, value in (("a scene name", getattr(args, "scene", None)), ("--mesh", args.mesh), ("--spec", spec))
        if value is not None
    ]
    if len(given) > 1:
        raise CliError(f"give one of a scene name, --mesh or --spec, not {' and '.join(given)}")
    if spec is not None:
        if args.kind is not None:  # the spec names its builder
            raise CliError("--kind goes with --mesh, not --spec (a spec's scene_params name its builder)")
        return _scene_from_spec_file(spec, params)
    if args.mesh is None:
        if args.kind is not None:
            raise CliError("--kind needs --mesh PATH")
        if getattr(args, "scene", None) is None:
            raise CliError("give a scene name, a mesh with --mesh PATH --kind fem|tets|cloth, or --spec FILE")
        return build_scene(args.scene, params)
    if args.kind is None:
        raise CliError("--mesh needs --kind fem|tets|cloth")
    try:
        return mesh_scene(args.kind, args.mesh, **params)
    except (FileNotFoundError, TypeError, ValueError) as err:
        raise CliError(f"cannot build a {args.kind} scene from {args.mesh}: {err}") from err


def _scene_from_spec_file(path: str, params: dict[str, Any]) -> Scene:
    from redsim.scenes.spec import SceneSpecError, read_spec, scene_from_spec

    if params:
        raise CliError("--param does not apply to --spec: the spec holds the scene's parameters")
    try:
        read_spec(path)  # an unreadable file says so without "cannot build"
    except SceneSpecError as err:
        raise CliError(str(err)) from err
    try:
        return scene_from_spec(path)  # a relative mesh path is the spec file's folder's
    except (SceneSpecError, TypeError, ValueError) as err:
        raise CliError(f"cannot build the scene of {path}: {err}") from err


def add_bench_scene_args(parser: argparse.ArgumentParser, default: str) -> None:
    """``--scenes A,B,...`` (default: ``default``), or one scene from ``--mesh PATH --kind fem|tets|cloth``."""
    parser.add_argument("--scenes", metavar="A,B,...", help=f"comma-separated scene names (default: {default})")
    _add_mesh_args(parser)


def bench_scenes(args: argparse.Namespace, default: Sequence[str]) -> list[tuple[str, Callable[[], Scene]]]:
    """(name, builder) of each scene a bench runs on: the ``--mesh`` scene, or ``--scenes`` (checked up front)."""
    if args.mesh is not None:
        if args.scenes is not None:
            raise CliError("give either --scenes or --mesh, not both")
        scene = scene_from_args(args)
        return [(scene.name, lambda: scene)]
    if args.kind is not None or args.param:
        raise CliError("--kind and --param go with --mesh (the --scenes are built with their defaults)")
    names = parse_list(args.scenes, "--scenes") if args.scenes is not None else list(default)
    for name in names:
        check_scene_name(name)
    return [(name, lambda name=name: build_scene(name)) for name in names]


def load_checkpoint(path: str) -> tuple[Scene, Any]:
    """The scene a checkpoint was fitted to (rebuilt from its JSON, a user's mesh included) and the subspace."""
    from redsim.scenes.spec import SceneSpecError, scene_from_spec
    from redsim.subspace import CheckpointError, checkpoint_path, load_subspace, read_metadata
    from redsim.subspace.checkpoint import beside_checkpoint

    if (why := beside_checkpoint(path)) is not None:  # a file beside a checkpoint, given in its place
        raise CliError(why)
    weights = checkpoint_path(path, ".pt")
    if weights.name.endswith(".fit.pt") and not weights.with_suffix(".json").is_file():  # a fit's resumable state
        mapped = weights.with_name(weights.name[: -len(".fit.pt")] + ".pt")
        raise CliError(
            f"{weights} is a fit's training state, not a checkpoint: "
            + (
                f"the fitted map is {mapped}"
                if mapped.is_file()
                else f"the fit is unfinished; `redsim fit ... --resume` finishes it into {mapped}"
            )
        )
    try:
        if not weights.is_file() and Path(path).suffix not in (".pt", ".json") and Path(path).exists():
            kind = "a folder" if Path(path).is_dir() else "a file"
            raise CliError(f"{path} is {kind}, not a checkpoint: give a fit's STEM.pt (STEM.json beside it) or STEM")
        if not weights.is_file():
            state = checkpoint_path(path, ".fit.pt")
            unfinished = f" ({state} holds an unfinished fit: `redsim fit ... --resume` finishes it)"
            raise CheckpointError("the weights file is missing" + unfinished * state.is_file(), str(weights))
        read_metadata(path)  # a missing or corrupt .json says so as a checkpoint's
        try:
            scene = scene_from_spec(weights)  # its .json: a relative mesh path is its folder's
        except (SceneSpecError, TypeError, ValueError) as err:
            raise SceneNotRebuilt(f"{weights}: cannot rebuild the checkpoint's scene: {err}") from err
        return scene, load_subspace(path, scene=scene)
    except CheckpointError as err:
        raise CliError(str(err)) from err
