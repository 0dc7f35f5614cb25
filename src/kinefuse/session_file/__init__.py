"""Session files: a TOML description of one recording and how to process it.

:func:`load_session` parses and validates a session file into a frozen :class:`SessionConfig`
(:mod:`~kinefuse.session_file.load`, one parser per section; the dataclasses in
:mod:`~kinefuse.session_file.config`); every problem is a
:class:`~kinefuse.exceptions.ConfigError` naming the file, the section and key, what was wrong
and how to fix it. :func:`session_template` (:mod:`~kinefuse.session_file.template`) returns the
commented template that ``kinefuse init-session`` writes. Relative paths in a session file are
resolved against the folder of the TOML file, so a session folder can be moved as a whole. The
``[method] name`` choices come from the registry :mod:`kinefuse.methods`.
"""

from kinefuse.session_file import config
from kinefuse.session_file._checks import _Ctx
from kinefuse.session_file.config import *  # noqa: F403 - the dataclasses and the choices
from kinefuse.session_file.load import init_session_hint, load_session, read_toml
from kinefuse.session_file.template import session_template

__all__ = [
    *config.__all__,
    "init_session_hint",
    "load_session",
    "read_toml",
    "session_template",
    "_Ctx",
]
