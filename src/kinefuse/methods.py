"""The method registry: every processing method kinefuse offers, in one place.

One :class:`Method` per name: what it needs (IMU, camera, reference), which forms exist
(``"offline"``: a batch run over a recording that may read later samples; ``"causal"``: a batch
run whose output at t reads inputs up to t only; ``"online"``: a streaming processor of
:mod:`kinefuse.streaming`, named by :attr:`Method.online`), its table label, a one-line summary
and the paper. Session loading (:mod:`kinefuse.session_file`), the session template, the
session processing (:mod:`kinefuse.pipelines.run`), the streaming configuration
(:mod:`kinefuse.streaming.config`), the CLI help and the experiments read it; the implementation
tables (:data:`kinefuse.pipelines.METHODS`, :data:`kinefuse.pipelines.UPPER_LIMB_METHODS`, the
streaming processors) are checked against it by the tests.

This module is pure data: it imports nothing from kinefuse but the exceptions.

Examples
--------
>>> from kinefuse import methods
>>> methods.names(form="online")
('paper-a', 'elm-fir', 'elm-kf')
>>> methods.get("elm-fir").needs
('imu', 'camera')
"""

from __future__ import annotations

from dataclasses import dataclass

from kinefuse._validation import did_you_mean
from kinefuse.exceptions import ConfigError

__all__ = [
    "BASELINES",
    "FILTERS",
    "FORMS",
    "INPUTS",
    "PROCESSORS",
    "REGISTRY",
    "Method",
    "get",
    "help_lines",
    "names",
    "unknown_fix",
]

#: Forms a method can exist in.
FORMS = ("offline", "causal", "online")
#: Inputs a method can need.
INPUTS = ("imu", "camera", "reference")

PAPER_A = "Sun et al. 2024, Micromachines 15, 440 (EM-KF/FIR)"
PAPER_B = "Xu et al. 2023, Micromachines 14, 2088 (ELM/FIR)"


@dataclass(frozen=True)
class Method:
    """One registered method.

    Attributes
    ----------
    name : str
        The name a session's ``[method] name`` and ``--method`` take.
    label : str
        Table label of its results.
    needs : tuple of str
        :data:`INPUTS` it cannot run without.
    forms : tuple of str
        :data:`FORMS` that exist.
    summary : str
        What it does, one line.
    paper : str or None
        The paper it implements (None: kinefuse's own or a plain baseline).
    online : str or None
        Name of its streaming processor (:data:`PROCESSORS`) when ``"online"`` is a form.
    online_substitute : str or None
        Without an online form: the processor streaming runs instead (with a warning), or None
        (streaming refuses the method).
    """

    name: str
    label: str
    needs: tuple[str, ...]
    forms: tuple[str, ...]
    summary: str
    paper: str | None = None
    online: str | None = None
    online_substitute: str | None = None

    @property
    def uses(self) -> str:
        """What it uses, as the template and error messages say it: ``"IMUs + camera"``."""
        words = {"imu": "IMUs", "camera": "camera", "reference": "reference"}
        return " + ".join(words[n] for n in self.needs)


# fmt: off
_TABLE = (
    # name, label, needs, forms, online (or None), online substitute (or None), paper, summary
    ("paper-a", "EM-KF/FIR", "imu", "offline causal online", "paper-a", None, PAPER_A,
     "EM-KF/FIR integrated filter on the IMU chain (Sun et al. 2024)"),
    ("elm-fir", "ELM/FIR", "imu camera", "offline causal online", "elm-fir", None, PAPER_B,
     "ELM/FIR with IMM fusion of chain and camera (Xu et al. 2023)"),
    ("elm-kf", "ELM/KF", "imu camera", "offline causal online", "elm-kf", None, PAPER_B,
     "the ELM/KF baseline of Xu et al. 2023"),
    ("imu-only", "IMU only", "imu", "offline causal", None, "paper-a", None,
     "forward kinematics of the IMU chain, no filtering"),
    ("camera-only", "camera only", "camera", "offline", None, None, None,
     "the camera joints alone, gaps interpolated (a baseline)"),
    ("kinefuse", "kinefuse", "imu camera", "offline causal", None, None, None,
     "kinefuse's chain + camera fusion with a learned chain-error model"),
    ("offset-interp", "offset interp", "imu camera", "offline", None, None, None,
     "baseline: IMU chain + camera-chain offset interpolated across outages (offline)"),
    ("offset-hold", "offset hold", "imu camera", "offline causal", None, None, None,
     "baseline: IMU chain + mean offset of the last 5 camera samples (causal)"),
    ("camera-gapfill", "camera gap-fill", "camera", "offline", None, None, None,
     "the camera, gaps up to 20 frames linearly interpolated (as Pose2Sim)"),
)
# fmt: on

#: The registry: name -> :class:`Method`, in the order help texts and templates list them.
REGISTRY: dict[str, Method] = {
    name: Method(
        name, label, tuple(needs.split()), tuple(forms.split()), summary, paper, online, substitute
    )  # fmt: skip
    for name, label, needs, forms, online, substitute, paper, summary in _TABLE
}

#: The simple baselines run beside every camera method, in report order.
BASELINES = ("camera-gapfill", "offset-interp", "offset-hold")

#: Paper A's filters (``[method.parameters] filter`` of ``paper-a`` / ``imu-only``): name ->
#: table label. ``"em-kf-fir"`` is paper A's integrated filter, the others its baselines.
FILTERS = {"kf": "KF", "fir": "FIR", "em-kf": "EM-KF", "em-kf-fir": "EM-KF/FIR"}

#: Streaming processors (:mod:`kinefuse.streaming`): name -> what it runs. Every
#: :attr:`Method.online` is one; ``"kf-fusion"`` is a processor of its own (no offline form).
PROCESSORS = {
    "kf-fusion": "IMU + camera fusion baseline: one constant-velocity Kalman filter per joint",
    "paper-a": "paper A's EM-KF/FIR integrated filter per joint on the IMU chain",
    "elm-fir": "paper B's ELM/FIR, step by step",
    "elm-kf": "paper B's ELM/KF baseline, step by step",
}


def names(*, form: str | None = None, needs: str | None = None) -> tuple[str, ...]:
    """Registered method names, in registry order.

    Parameters
    ----------
    form : str, optional
        Only methods with this :data:`FORMS` entry.
    needs : str, optional
        Only methods that need this :data:`INPUTS` entry.

    Returns
    -------
    tuple of str
    """
    if form is not None and form not in FORMS:
        raise ConfigError(f"expected form in {FORMS}, got {form!r}")
    if needs is not None and needs not in INPUTS:
        raise ConfigError(f"expected needs in {INPUTS}, got {needs!r}")
    return tuple(
        m.name
        for m in REGISTRY.values()
        if (form is None or form in m.forms) and (needs is None or needs in m.needs)
    )


#: Names people reach for that are not method names (normalised: lower case, no ``-``, ``_``
#: or spaces), and what to use instead.
_POINTERS = {
    "paperb": "paper B's methods are 'elm-fir' (its proposed ELM/FIR fusion) and 'elm-kf'",
    "imu": "did you mean 'imu-only'?",
    "camera": "did you mean 'camera-only'?",
}


def unknown_fix(name, choices=None) -> str:
    """What to say about an unknown method ``name``: a pointer for names people reach for
    (``"paper-b"`` → its methods ``elm-fir`` / ``elm-kf``), else the closest of ``choices``
    (default every registered name)."""
    key = "".join(c for c in str(name).lower() if c not in "-_ ")
    if key in _POINTERS:
        return _POINTERS[key]
    return did_you_mean(str(name), list(choices if choices is not None else REGISTRY))


def get(name: str) -> Method:
    """The :class:`Method` called ``name``.

    Raises
    ------
    ConfigError
        Unknown name (with the closest registered one, if any).
    """
    method = REGISTRY.get(name)
    if method is None:
        raise ConfigError(f"unknown method {name!r} ({unknown_fix(name)})")
    return method


def help_lines(*, form: str | None = None) -> list[str]:
    """One line per method, ``"name  uses  : summary [forms]"``, e.g. for ``--help`` texts."""
    chosen = names(form=form)
    w = max(len(n) for n in chosen)
    return [
        f"{n:<{w}}  {REGISTRY[n].uses:<14}: {REGISTRY[n].summary} [{', '.join(REGISTRY[n].forms)}]"
        for n in chosen
    ]
