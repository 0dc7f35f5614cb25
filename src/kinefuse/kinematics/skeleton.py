"""Skeleton: a parent-index tree of rigid segments with lengths, sensor-frame axes and root offsets.

SPEC §2.1 (paper A: shoulder root, upper arm, forearm) and §2.2 (paper B: chest origin with
shoulder and hip offsets, upper arms, forearms, thighs, shanks). Lengths come, in this order of
preference, from measurement (``lengths=``), from reference or vision data
(:meth:`Skeleton.with_lengths_from` / :func:`lengths_from_joints`), or from anthropometric
ratios of body height (:data:`ANTHROPOMETRIC_RATIOS`, SPEC §2.2); :func:`segment_lengths`
applies that order and says where each length came from.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from kinefuse._validation import as_float
from kinefuse.exceptions import InputError
from kinefuse.io.recording import JointStream

__all__ = [
    "ANTHROPOMETRIC_RATIOS",
    "AXES",
    "Skeleton",
    "full_body",
    "lengths_from_joints",
    "lower_body",
    "segment_lengths",
    "upper_limb",
]

#: Segment lengths as fractions of body height H: Winter, D. A. (2009), *Biomechanics and Motor
#: Control of Human Movement*, 4th ed., Wiley, Fig. 4.1 (after Drillis & Contini 1966): upper
#: arm 0.186 H, forearm 0.146 H, thigh 0.245 H (greater trochanter 0.530 H to knee 0.285 H),
#: shank ("leg") 0.246 H (knee to ankle 0.039 H), shoulder width 0.259 H, hip width 0.191 H
#: (SPEC §2.2 [U]). Population means; an individual's segments differ from them by several
#: per cent, so measured lengths are preferred.
ANTHROPOMETRIC_RATIOS = {
    "upper_arm": 0.186,
    "forearm": 0.146,
    "thigh": 0.245,
    "shank": 0.246,
    "shoulder_width": 0.259,
    "hip_width": 0.191,
    # Not in SPEC: vertical distance shoulder (acromion, 0.818 H) to hip joint (greater
    # trochanter, 0.530 H), Winter 2009 Fig. 4.1 [U]; only used by full_body() without data.
    "chest_to_hip": 0.288,
    # Not in SPEC: hip joint centre spacing, 0.167 m in OpenSim's gait2392 (Delp et al. 1990;
    # hip_r z = 0.0835 m) for 1.80 m: 0.0928 H. SPEC's 0.191 H is the breadth across the hips
    # (Neura's Vicon hip centres: 0.185 m apart). Used by kinefuse run (pipelines.run.chain).
    "hip_joint_spacing": 0.0928,
    # Not in SPEC: shoulder (glenohumeral) joint spacing, 0.34 m in OpenSim's full-body models
    # (Hamner et al. 2010; acromial_r z = 0.17 m) at the same 1.80 m: 0.189 H; SPEC's 0.259 H
    # is the breadth across the shoulders. Used by kinefuse run (pipelines.run.chain).
    "shoulder_joint_spacing": 0.189,
}

#: Named unit axes accepted wherever a segment axis is configured (SPEC §2.2-1: ±e1, ±e2, ±e3).
AXES = {
    "+e1": (1.0, 0.0, 0.0),
    "-e1": (-1.0, 0.0, 0.0),
    "+e2": (0.0, 1.0, 0.0),
    "-e2": (0.0, -1.0, 0.0),
    "+e3": (0.0, 0.0, 1.0),
    "-e3": (0.0, 0.0, -1.0),
}
AXES.update({k[1:]: v for k, v in list(AXES.items()) if k[0] == "+"})


def unit_axis(value, where: str) -> np.ndarray:
    """``value`` (an :data:`AXES` name such as ``"+e2"`` or a 3-vector) as a unit vector (3,).

    ``where`` names the setting in the InputError raised for an unknown name or a zero vector.
    """
    if isinstance(value, str):
        if value not in AXES:
            raise InputError(
                f"{where}: unknown axis name {value!r}; expected one of {sorted(AXES)}"
            )
        return np.array(AXES[value], dtype=float)
    a = np.asarray(value, dtype=float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InputError(f"{where}: expected a finite axis with shape (3,), got {a.shape}")
    n = float(np.linalg.norm(a))
    if n < 1e-9:
        raise InputError(f"{where}: expected a non-zero axis, got {a}")
    return a / n


def _length(value, where: str) -> float:
    v = as_float(value, f"{where}: expected a length in metres, got {value!r}")
    if not np.isfinite(v) or v < 0:
        raise InputError(f"{where}: expected a finite length >= 0 m, got {v}")
    if v > 3.0:
        raise InputError(f"{where}: expected a length in metres (< 3 m), got {v}; millimetres?")
    return v


@dataclass(frozen=True, eq=False)
class Skeleton:
    """Segments of a kinematic chain, as a parent-index tree.

    Attributes
    ----------
    segments : tuple of str
        Segment names (canonical, :data:`kinefuse.conventions.SEGMENTS`), parents before children.
    parents : tuple of int
        Index of each segment's parent in ``segments``; ``-1`` = starts at a root joint (the root
        itself or one of the ``offsets`` joints).
    proximal, distal : tuple of str
        Joint names at the proximal and distal end of each segment (e.g. ``hip_l`` -> ``knee_l``).
        A child's proximal joint is its parent's distal joint.
    lengths_m : tuple of float
        Segment lengths, m (proximal -> distal joint distance).
    axes : ndarray, shape (S, 3)
        Unit segment axis (proximal -> distal) expressed in the frame of the orientation that
        drives the segment: the IMU (sensor) frame when IMU orientations are passed (default
        ``e2``, paper B's convention, SPEC §2.2-1), the segment frame for segment orientations.
    root : str
        Name of the root joint (origin of the chain): ``shoulder_r`` (paper A), ``pelvis``,
        ``spine_shoulder`` (paper B's upper-chest origin).
    root_segment : str or None
        Segment whose orientation rotates the ``offsets`` (``chest``, ``pelvis``); None if the
        skeleton has no offsets.
    offsets_m : dict of str -> ndarray, shape (3,)
        Joints rigidly attached to the root, as vectors from the root joint in the
            ``root_segment`` frame (right-front-up for paper B's chest IMU), m. An all-NaN offset
        means "unknown": that joint must then be supplied as a root position.
    """

    segments: tuple[str, ...]
    parents: tuple[int, ...]
    proximal: tuple[str, ...]
    distal: tuple[str, ...]
    lengths_m: tuple[float, ...]
    axes: np.ndarray
    root: str
    root_segment: str | None = None
    offsets_m: Mapping[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        S = len(self.segments)
        for name in ("parents", "proximal", "distal", "lengths_m"):
            if len(getattr(self, name)) != S:
                raise InputError(
                    f"skeleton: expected {S} {name} (one per segment), got {len(getattr(self, name))}"
                )
        if len(set(self.segments)) != S:
            raise InputError(f"skeleton: duplicate segment names in {self.segments}")
        object.__setattr__(self, "segments", tuple(self.segments))
        object.__setattr__(self, "parents", tuple(int(p) for p in self.parents))
        object.__setattr__(self, "proximal", tuple(self.proximal))
        object.__setattr__(self, "distal", tuple(self.distal))
        object.__setattr__(
            self,
            "lengths_m",
            tuple(
                _length(v, f"skeleton: length of {s!r}")
                for s, v in zip(self.segments, self.lengths_m, strict=True)
            ),
        )
        axes = np.asarray(self.axes, dtype=float)
        if axes.shape != (S, 3):
            raise InputError(
                f"skeleton: expected axes with shape (S, 3) = ({S}, 3), got {axes.shape}"
            )
        axes = (
            np.stack(
                [
                    unit_axis(a, f"skeleton: axis of {s!r}")
                    for s, a in zip(self.segments, axes, strict=True)
                ]
            )
            if S
            else axes
        )
        axes.setflags(write=False)
        object.__setattr__(self, "axes", axes)
        offs = {}
        for j, v in dict(self.offsets_m).items():
            o = np.asarray(v, dtype=float)
            if o.shape != (3,) or not (np.all(np.isfinite(o)) or np.all(np.isnan(o))):
                raise InputError(
                    f"skeleton: expected offset of {j!r} with shape (3,), finite (or all NaN = unknown, to be "
                    f"supplied as a root position), got {o}"
                )
            o.setflags(write=False)
            offs[j] = o
        object.__setattr__(self, "offsets_m", offs)
        if offs and self.root_segment is None:
            raise InputError(
                "skeleton: offsets need a root_segment whose orientation rotates them, got None"
            )
        starts = {self.root, *offs}
        for i, (p, prox) in enumerate(zip(self.parents, self.proximal, strict=True)):
            if p == -1:
                if prox not in starts:
                    raise InputError(
                        f"skeleton: segment {self.segments[i]!r} has no parent, so its proximal joint must be the "
                        f"root or an offset joint {sorted(starts)}, got {prox!r}"
                    )
            elif not 0 <= p < i:
                raise InputError(
                    f"skeleton: expected parent index of {self.segments[i]!r} in [-1, {i - 1}] (parents first), got {p}"
                )
            elif self.distal[p] != prox:
                raise InputError(
                    f"skeleton: segment {self.segments[i]!r} starts at {prox!r} but its parent "
                    f"{self.segments[p]!r} ends at {self.distal[p]!r}"
                )

    # ------------------------------------------------------------------ lookups
    def index(self, segment: str) -> int:
        """Index of ``segment``; a clear error lists the known names."""
        try:
            return self.segments.index(segment)
        except ValueError:
            raise InputError(
                f"unknown segment {segment!r}; this skeleton has {list(self.segments)}"
            ) from None

    @property
    def joints(self) -> tuple[str, ...]:
        """All joint names: root, offset joints, then the distal joint of each segment."""
        out = [self.root, *self.offsets_m]
        out += [j for j in self.distal if j not in out]
        return tuple(out)

    def length(self, segment: str) -> float:
        """Length of ``segment``, m."""
        return self.lengths_m[self.index(segment)]

    def axis(self, segment: str) -> np.ndarray:
        """Unit axis of ``segment`` in its sensor frame, shape (3,)."""
        return self.axes[self.index(segment)].copy()

    def __len__(self) -> int:
        return len(self.segments)

    # ------------------------------------------------------------------ updates
    def _check_keys(self, values: Mapping, what: str) -> None:
        unknown = sorted(set(values) - set(self.segments))
        if unknown:
            raise InputError(
                f"{what}: unknown segment(s) {unknown}; expected names from {list(self.segments)}"
            )

    def with_lengths(self, lengths: Mapping[str, float]) -> Skeleton:
        """A copy with the given segment lengths (m) replaced; others kept."""
        self._check_keys(lengths, "with_lengths")
        new = tuple(
            float(lengths.get(s, v)) for s, v in zip(self.segments, self.lengths_m, strict=True)
        )
        return replace(self, lengths_m=new)

    def with_axes(self, axes: Mapping[str, object]) -> Skeleton:
        """A copy with the given segment axes (3-vectors or names ``"+e1"``, ``"-e2"``...) replaced."""
        self._check_keys(axes, "with_axes")
        new = np.array(self.axes)
        for s, a in axes.items():
            new[self.index(s)] = unit_axis(a, f"with_axes: axis of {s!r}")
        return replace(self, axes=new)

    def with_offsets(self, offsets: Mapping[str, object]) -> Skeleton:
        """A copy with the given root offsets (m, root-segment frame) replaced or added."""
        new = dict(self.offsets_m)
        new.update({j: np.asarray(v, dtype=float) for j, v in offsets.items()})
        return replace(self, offsets_m=new)

    def with_lengths_from(
        self, stream: JointStream, *, start_s: float | None = None, window_s: float | None = None
    ) -> Skeleton:
        """A copy with lengths = median joint distance in ``stream`` (see :func:`lengths_from_joints`).

        Segments whose joints the stream lacks keep their current length.
        """
        return self.with_lengths(
            lengths_from_joints(stream, self, start_s=start_s, window_s=window_s, missing="skip")
        )

    @classmethod
    def from_joint_stream(
        cls,
        stream: JointStream,
        preset: str = "lower_body",
        *,
        start_s: float | None = None,
        window_s: float | None = None,
        **preset_kwargs,
    ) -> Skeleton:
        """Build a preset skeleton and take its lengths from reference/vision joints.

        Parameters
        ----------
        stream : JointStream
            Joint positions (m) naming the preset's joints (canonical names).
        preset : {"upper_limb", "lower_body", "full_body"}
            Topology; ``preset_kwargs`` go to the preset (``side=``, ``axes=``, ``height_m=``...).
        start_s, window_s : float, optional
            Time window for the median bone lengths (default: the whole stream).

        Notes
        -----
        All segment lengths must be measurable from the stream (else ValueError naming the
        missing joints). Offsets of presets with a root segment are kept from ``preset_kwargs``.
        """
        presets = {"upper_limb": upper_limb, "lower_body": lower_body, "full_body": full_body}
        if preset not in presets:
            raise InputError(
                f"unknown skeleton preset {preset!r}; expected one of {sorted(presets)}"
            )
        fn = presets[preset]
        kw = dict(preset_kwargs)
        names = fn(
            **{k: v for k, v in kw.items() if k in ("side",)}, lengths=None, height_m=1.7
        ).segments
        kw["lengths"] = {
            **dict.fromkeys(names, 0.0),
            **dict(kw.get("lengths") or {}),
        }  # replaced below
        template = fn(**kw)
        lengths = lengths_from_joints(
            stream, template, start_s=start_s, window_s=window_s, missing="raise"
        )
        return template.with_lengths(lengths)


def lengths_from_joints(
    stream: JointStream,
    skeleton: Skeleton | Sequence[tuple[str, str, str]],
    *,
    start_s: float | None = None,
    window_s: float | None = None,
    missing: str = "raise",
) -> dict[str, float]:
    """Median bone lengths from joint positions (reference or vision), m.

    Parameters
    ----------
    stream : JointStream
        Joint positions, m.
    skeleton : Skeleton or sequence of (segment, proximal_joint, distal_joint)
        Which joint pairs define which segment.
    start_s, window_s : float, optional
        Use samples with ``start_s <= t < start_s + window_s`` (defaults: first sample, all).
    missing : {"raise", "skip"}
        What to do when the stream lacks a joint or has no sample where both are available.

    Returns
    -------
    dict of str -> float
        ``median_k ‖p_distal(k) − p_proximal(k)‖`` per segment over the available samples.
    """
    if not isinstance(stream, JointStream):
        raise InputError(f"expected stream as a JointStream, got {type(stream).__name__}")
    if missing not in ("raise", "skip"):
        raise InputError(f"expected missing in ('raise', 'skip'), got {missing!r}")
    pairs = (
        list(zip(skeleton.segments, skeleton.proximal, skeleton.distal, strict=True))
        if isinstance(skeleton, Skeleton)
        else list(skeleton)
    )
    sel = window_mask(stream.t_s, start_s, window_s)
    out = {}
    for seg, a, b in pairs:
        if a not in stream.joints or b not in stream.joints:
            if missing == "skip":
                continue
            lack = [j for j in (a, b) if j not in stream.joints]
            raise InputError(
                f"segment {seg!r}: expected joints {lack} in the joint stream for its length, got {list(stream.joints)}"
            )
        d = stream.position(b)[sel] - stream.position(a)[sel]
        n = np.linalg.norm(d, axis=1)
        n = n[np.isfinite(n)]
        if n.size == 0:
            if missing == "skip":
                continue
            raise InputError(
                f"segment {seg!r}: no sample in the window where both {a!r} and {b!r} are available"
            )
        out[seg] = float(np.median(n))
    return out


def window_mask(t_s: np.ndarray, start_s: float | None, window_s: float | None) -> np.ndarray:
    """Boolean mask of samples with ``start_s <= t < start_s + window_s`` (defaults: all)."""
    t = np.asarray(t_s, dtype=float)
    t0 = float(t[0]) if start_s is None else float(start_s)
    sel = t >= t0 - 1e-9
    if window_s is not None:
        if not np.isfinite(window_s) or window_s <= 0:
            raise InputError(f"expected window_s finite and > 0, got {window_s}")
        sel &= t < t0 + float(window_s) - 1e-9
    if not np.any(sel):
        raise InputError(
            f"expected a window with samples, got start_s={t0}, window_s={window_s} for times "
            f"[{t[0]:.3f}, {t[-1]:.3f}] s"
        )
    return sel


def segment_lengths(
    segments: Sequence[str],
    *,
    measured: Mapping[str, float] | None = None,
    height_m: float | None = None,
    functional: Mapping[str, float] | None = None,
    derived: Mapping[str, tuple[float, str]] | None = None,
) -> tuple[dict[str, float], dict[str, str]]:
    """Length of each segment and where it came from, in kinefuse's order of preference.

    Parameters
    ----------
    segments : sequence of str
        Canonical segment names (``thigh_l``, ``forearm_r``...).
    measured : mapping of str -> float, optional
        Measured (tape) lengths, m; always win.
    height_m : float, optional
        Body height, m: :data:`ANTHROPOMETRIC_RATIOS` (Winter 2009) times the height.
    functional : mapping of str -> float, optional
        Lengths estimated from movement (functional calibration), m; used where neither a
        measurement nor the height gives one.
    derived : mapping of str -> (float, str), optional
        Lengths the user asked to take from data (e.g. the reference), with their source text;
        used after the measured ones and before the height.

    Returns
    -------
    lengths : dict of str -> float
        m.
    sources : dict of str -> str
        ``"measured"``, the ``derived`` source, ``"body height 1.75 m x 0.245 (Winter 2009)"``
        or ``"functional calibration"``.

    Raises
    ------
    ValueError (:class:`kinefuse.exceptions.InputError`)
        A segment none of them gives a length for; the message names it and the fixes.
    """
    measured = dict(measured or {})
    derived = dict(derived or {})
    functional = dict(functional or {})
    h = _height(height_m)
    out, how = {}, {}
    for seg in segments:
        kind = seg.rsplit("_", 1)[0] if seg[-2:] in ("_l", "_r") else seg
        if seg in measured:
            out[seg], how[seg] = _length(measured[seg], f"measured length of {seg!r}"), "measured"
        elif seg in derived:
            v, src = derived[seg]
            out[seg], how[seg] = _length(v, f"length of {seg!r} from {src}"), src
        elif h is not None and kind in ANTHROPOMETRIC_RATIOS:
            r = ANTHROPOMETRIC_RATIOS[kind]
            out[seg], how[seg] = r * h, f"body height {h:g} m x {r:g} (Winter 2009)"
        elif seg in functional:
            out[seg], how[seg] = (
                _length(functional[seg], f"functional length of {seg!r}"),
                "functional calibration",
            )
    missing = [s for s in segments if s not in out]
    if missing:
        no_ratio = [s for s in missing if s.rsplit("_", 1)[0] not in ANTHROPOMETRIC_RATIOS]
        height = "" if len(no_ratio) == len(missing) else ", give body_height_m"
        hint = f"; {no_ratio} have no anthropometric ratio, so body height cannot give them"
        raise InputError(
            f"no length for segment(s) {missing}: measure them ([skeleton.lengths] in m)"
            f"{height}, or use functional calibration{hint if no_ratio else ''}"
        )
    return out, how


# ---------------------------------------------------------------------- presets
def _pick_lengths(
    names: Sequence[tuple[str, str]], lengths, height_m, where: str
) -> dict[str, float]:
    """Segment name -> length from explicit ``lengths`` (preferred) else ``height_m`` ratios."""
    lengths = dict(lengths or {})
    known = {s for s, _ in names}
    unknown = sorted(set(lengths) - known)
    if unknown:
        raise InputError(
            f"{where}: unknown segment(s) {unknown} in lengths; expected names from {sorted(known)}"
        )
    out = {}
    for seg, kind in names:
        if seg in lengths:
            out[seg] = float(lengths[seg])
        elif height_m is not None:
            out[seg] = ANTHROPOMETRIC_RATIOS[kind] * float(height_m)
        else:
            raise InputError(
                f"{where}: no length for {seg!r}: give lengths={{...}} (measured, preferred), lengths from "
                "reference/vision data (Skeleton.from_joint_stream) or height_m for anthropometric ratios"
            )
    return out


def _height(height_m) -> float | None:
    if height_m is None:
        return None
    h = float(height_m)
    if not np.isfinite(h) or not 0.5 < h < 2.8:
        raise InputError(f"expected height_m in metres (0.5-2.8), got {height_m!r}")
    return h


def _axes_for(segments: Sequence[str], axes, where: str) -> np.ndarray:
    """Per-segment axes from None (all e2), one axis for all, or a mapping segment -> axis."""
    if axes is None:
        return np.tile(np.array(AXES["+e2"]), (len(segments), 1))
    if isinstance(axes, Mapping):
        unknown = sorted(set(axes) - set(segments))
        if unknown:
            raise InputError(
                f"{where}: unknown segment(s) {unknown} in axes; expected names from {list(segments)}"
            )
        return np.stack(
            [unit_axis(axes.get(s, "+e2"), f"{where}: axis of {s!r}") for s in segments]
        )
    a = unit_axis(axes, f"{where}: axes")
    return np.tile(a, (len(segments), 1))


def _side(side: str) -> str:
    s = str(side).lower()
    aliases = {"l": "l", "left": "l", "r": "r", "right": "r"}
    if s not in aliases:
        raise InputError(f"expected side in ('l', 'r', 'left', 'right'), got {side!r}")
    return aliases[s]


def upper_limb(side: str = "r", *, lengths=None, height_m=None, axes=None) -> Skeleton:
    """Paper A's chain (SPEC §2.1): shoulder root -> upper arm -> forearm.

    Parameters
    ----------
    side : {"r", "l"}
        Arm.
    lengths : mapping, optional
        ``{"upper_arm_r": l1, "forearm_r": l2}``, m (measured; preferred).
    height_m : float, optional
        Body height, m, for anthropometric lengths (0.186 H, 0.146 H) where ``lengths`` lacks one.
    axes : axis or mapping, optional
        Segment axis in the IMU frame, one for all or per segment (default ``e2``).

    Returns
    -------
    Skeleton
        Root ``shoulder_<side>`` (measured, e.g. from the camera, paper A §4.1), segments
        ``upper_arm_<side>`` (shoulder -> elbow) and ``forearm_<side>`` (elbow -> wrist).
    """
    s = _side(side)
    segs = (f"upper_arm_{s}", f"forearm_{s}")
    L = _pick_lengths(
        list(zip(segs, ("upper_arm", "forearm"), strict=True)),
        lengths,
        _height(height_m),
        "upper_limb",
    )
    return Skeleton(
        segments=segs,
        parents=(-1, 0),
        proximal=(f"shoulder_{s}", f"elbow_{s}"),
        distal=(f"elbow_{s}", f"wrist_{s}"),
        lengths_m=tuple(L[x] for x in segs),
        axes=_axes_for(segs, axes, "upper_limb"),
        root=f"shoulder_{s}",
    )


def lower_body(*, lengths=None, height_m=None, axes=None, hip_offsets=None) -> Skeleton:
    """Pelvis root with hip offsets, thighs and shanks.

    Parameters
    ----------
    lengths : mapping, optional
        ``thigh_l/r``, ``shank_l/r`` lengths, m.
    height_m : float, optional
        Body height for anthropometric lengths (thigh 0.245 H, shank 0.246 H, hip width 0.191 H).
    axes : axis or mapping, optional
        Segment axes in the IMU frames (default ``e2``).
    hip_offsets : mapping, optional
        ``{"hip_l": (3,), "hip_r": (3,)}`` from the pelvis origin in the pelvis-IMU frame, m.
        Default ``(∓w/2, 0, 0)`` with ``w`` = 0.191 ``height_m`` (right-front-up IMU frame) [J];
        unknown (NaN) without ``height_m``, so the hips must then be given as roots
        (``kinefuse run``: ``ANTHROPOMETRIC_RATIOS["hip_joint_spacing"]``, 0.0928 H).

    Notes
    -----
    When hip positions are supplied as roots (e.g. Vicon hip joint centres), the offsets and the
    pelvis orientation are not used.
    """
    segs = ("thigh_l", "shank_l", "thigh_r", "shank_r")
    h = _height(height_m)
    L = _pick_lengths(
        list(zip(segs, ("thigh", "shank", "thigh", "shank"), strict=True)), lengths, h, "lower_body"
    )
    if hip_offsets is None:
        if h is None:
            hip_offsets = {"hip_l": (np.nan,) * 3, "hip_r": (np.nan,) * 3}
        else:
            w = ANTHROPOMETRIC_RATIOS["hip_width"] * h
            hip_offsets = {"hip_l": (-w / 2, 0.0, 0.0), "hip_r": (w / 2, 0.0, 0.0)}
    return Skeleton(
        segments=segs,
        parents=(-1, 0, -1, 2),
        proximal=("hip_l", "knee_l", "hip_r", "knee_r"),
        distal=("knee_l", "ankle_l", "knee_r", "ankle_r"),
        lengths_m=tuple(L[x] for x in segs),
        axes=_axes_for(segs, axes, "lower_body"),
        root="pelvis",
        root_segment="pelvis",
        offsets_m=dict(hip_offsets),
    )


def full_body(*, lengths=None, height_m=None, axes=None, offsets=None) -> Skeleton:
    """Paper B's skeleton (SPEC §2.2 corrected form): chest origin, shoulder/hip offsets, 8 limb segments.

    Parameters
    ----------
    lengths : mapping, optional
        Lengths of ``upper_arm_l/r`` (l_E), ``forearm_l/r`` (l_W), ``thigh_l/r`` (l_k), ``shank_l/r``
        (l_a), m.
    height_m : float, optional
        Body height for anthropometric lengths and default offsets.
    axes : axis or mapping, optional
        Segment axes in the IMU frames (default ``e2``, SPEC §2.2-1).
    offsets : mapping, optional
        ``shoulder_l/r``, ``hip_l/r`` from the upper-chest origin in the chest-IMU frame b0, m.
        Default (right-front-up b0): shoulders ``(∓s/2, 0, 0)``, hips ``(∓w/2, 0, −c)`` with
        s = 0.259 H, w = 0.191 H, c = 0.288 H [J, U].

    Returns
    -------
    Skeleton
        Root ``spine_shoulder`` (paper B's "upper chest" origin), ``root_segment="chest"``.

    Notes
    -----
    Deviations from the paper (SPEC §2.2): positions are computed in ENU from absolute segment
    orientations, not from relative rotations into the chest frame; the segment axis is
    configurable (default e2 = paper's ",2" subscript, not the text's "first column"); the hip
    offsets ``Po_6`` (undefined in the paper) are constant offsets from the chest origin (rigid
    chest-pelvis, no pelvis IMU); 9 IMUs (chest + 8 limb segments), not 8.
    """
    segs = tuple(x[0] for x in _FULL_BODY)
    kinds = tuple(s[:-2] for s in segs)
    h = _height(height_m)
    L = _pick_lengths(list(zip(segs, kinds, strict=True)), lengths, h, "full_body")
    if offsets is None:
        offsets = _default_offsets(h)
    need = {"shoulder_l", "shoulder_r", "hip_l", "hip_r"}
    if set(offsets) != need:
        raise InputError(f"full_body: expected offsets for {sorted(need)}, got {sorted(offsets)}")
    return Skeleton(
        segments=segs,
        parents=(-1, 0, -1, 2, -1, 4, -1, 6),
        proximal=tuple(x[1] for x in _FULL_BODY),
        distal=tuple(x[2] for x in _FULL_BODY),
        lengths_m=tuple(L[x] for x in segs),
        axes=_axes_for(segs, axes, "full_body"),
        root="spine_shoulder",
        root_segment="chest",
        offsets_m=dict(offsets),
    )


#: Paper B's limb segments (segment, proximal joint, distal joint) in :func:`full_body` order.
_ARM = (("upper_arm", "shoulder", "elbow"), ("forearm", "elbow", "wrist"))
_LEG = (("thigh", "hip", "knee"), ("shank", "knee", "ankle"))
_FULL_BODY = tuple(
    (f"{seg}_{s}", f"{p}_{s}", f"{d}_{s}")
    for limb in (_ARM, _LEG)
    for s in "lr"
    for seg, p, d in limb
)


def _default_offsets(h: float | None) -> dict[str, tuple[float, float, float]]:
    """Shoulder and hip offsets from the chest origin scaled by body height ``h`` (m)."""
    if h is None:
        raise InputError(
            "full_body: no shoulder/hip offsets: give offsets={'shoulder_l': ..., 'shoulder_r': ..., "
            "'hip_l': ..., 'hip_r': ...} (m, chest frame) or height_m"
        )
    sw = ANTHROPOMETRIC_RATIOS["shoulder_width"] * h
    hw = ANTHROPOMETRIC_RATIOS["hip_width"] * h
    c = ANTHROPOMETRIC_RATIOS["chest_to_hip"] * h
    return {
        "shoulder_l": (-sw / 2, 0.0, 0.0),
        "shoulder_r": (sw / 2, 0.0, 0.0),
        "hip_l": (-hw / 2, 0.0, -c),
        "hip_r": (hw / 2, 0.0, -c),
    }
