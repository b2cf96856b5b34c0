"""The backends' command-line options, generated from what each backend kind declares (vlmproprio.kinds).

A kind's ``KindOption`` rows say the flag, the setting it sets, and per command (run, models, score) its help;
here they become argparse options, and the parsed values become backend settings. No flag is spelled here.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence


def _options(command: str, first: Sequence[str] = ()) -> list:
    """The kinds that have options in ``command``, with those options; kinds named in ``first`` lead."""
    from vlmproprio.kinds import kind_specs

    specs = sorted(kind_specs(), key=lambda s: (s.kind not in first, first.index(s.kind) if s.kind in first else 0))
    found = [(spec, [o for o in spec.options if command in o.helps]) for spec in specs]
    return [(spec, opts) for spec, opts in found if opts]


def setting_options() -> dict[str, str]:
    """Command-line option (argparse dest) -> backend setting: the one place the two vocabularies meet."""
    from vlmproprio.kinds import kind_specs

    return {o.dest: o.setting for spec in kind_specs() for o in spec.options}


def backend_settings(args: argparse.Namespace, **paths):
    """The backend settings a command's options give (those it has), plus ``paths`` (cassette_dir, home)."""
    from vlmproprio.backends.settings import BackendSettings

    given = {setting: getattr(args, dest) for dest, setting in setting_options().items() if hasattr(args, dest)}
    return BackendSettings.of(**given, **paths)


def add_backend_options(p: argparse.ArgumentParser) -> None:
    """run: one option group per backend kind, after the method's."""
    for spec, opts in _options("run"):
        g = p.add_argument_group(spec.option_group or f"{spec.kind} models")
        for o in opts:
            g.add_argument(o.flag, **o.argparse_kwargs("run"))


def add_kind_options(g, command: str, first: Sequence[str] = ()) -> None:
    """models, score: the backend kinds' options for ``command`` in one parser or group, kind after kind."""
    for _spec, opts in _options(command, first):
        for o in opts:
            g.add_argument(o.flag, **o.argparse_kwargs(command))
