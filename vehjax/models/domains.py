"""Physical domains of a model's parameters and the envelope of its states.

A built-in model declares, in one class-level mapping ``PARAM_DOMAINS``, the interval each of
its parameters must lie in, written as in mathematics: ``interval("(0, inf)")`` for a mass,
``interval("[0, inf)")`` for a drag coefficient that may be zero, ``interval("(0, 2)")`` for a
shape factor. A round bracket is an open end (the bound itself excluded), a square one a
closed end (included); an infinite end is always open. Each interval carries a note that says
why (a physical necessity or a convention of vehjax) and is shown in the error when a value
falls outside. :meth:`vehjax.models.BaseModel.param_domains` gathers them for the model's
parameters into a :class:`ParamDomains`, which the model's constructor, ``with_theta``,
:func:`vehjax.simulate` and :func:`vehjax.filter` / :func:`vehjax.run` (``theta0`` of a
state-only filter) check values against (:func:`vehjax.validation.in_domain`, before anything
is traced); :meth:`ParamDomains.bounds` gives the (low, high) arrays an optimiser bounds a fit
with.

The state envelope (``STATE_ENVELOPE``: state name -> largest plausible magnitude, in the
state's unit) is where :func:`vehjax.simulate` stops believing a run: far beyond anything a
road vehicle does (a lateral velocity of 300 m/s), so that it flags blow-ups of a model driven
outside its validity, not hard driving. States it does not name are only checked for
finiteness.
"""

from __future__ import annotations

import math

from typing import NamedTuple

import numpy as np

__all__ = ["Interval", "interval", "ParamDomains", "gather", "envelope", "extended"]


class Interval(NamedTuple):
    """One parameter's domain: ``low`` < or <= value < or <= ``high``.

    Attributes:
        low, high: the ends, -inf / +inf for an open-ended side.
        low_closed, high_closed: whether the end itself belongs to the domain (never for an
            infinite end).
        note: why the domain is what it is, shown in the error; may use ``{name}``,
            ``{value}`` and ``{minus}`` (the parameter, the offending value and its negative),
            e.g. to say how to convert a sign convention.
    """

    low: float
    high: float
    low_closed: bool = False
    high_closed: bool = False
    note: str = ""

    def text(self) -> str:
        """The interval as written in mathematics, e.g. ``(0, inf)`` or ``[0, 3]``."""
        return (f"{'[' if self.low_closed else '('}{_num(self.low)}, {_num(self.high)}"
                f"{']' if self.high_closed else ')'}")


def _num(v: float) -> str:
    return "inf" if v == math.inf else "-inf" if v == -math.inf else f"{v:g}"


def interval(text: str, note: str = "") -> Interval:
    """The :class:`Interval` written ``text``: ``"(0, inf)"``, ``"[0, inf)"``, ``"(0, 3]"``;
    ``inf`` / ``-inf`` for open ends. ValueError for anything else (a programming error)."""
    s = text.strip()
    if len(s) < 5 or s[0] not in "([" or s[-1] not in ")]" or s.count(",") != 1:
        raise ValueError(f"interval: expected e.g. '(0, inf)' or '[0, 3]', got {text!r}")
    low, high = (float(p) for p in s[1:-1].split(","))
    low_closed, high_closed = s[0] == "[", s[-1] == "]"
    if not low < high or (low_closed and math.isinf(low)) or (high_closed and math.isinf(high)):
        raise ValueError(f"interval: expected low < high and open infinite ends, got {text!r}")
    return Interval(low, high, low_closed, high_closed, note)


class ParamDomains(NamedTuple):
    """The domains of a model's parameters, in the order of ``param_names`` (hashable: tuples
    of Python numbers, so that it can be a static field of a jitted object).

    Attributes:
        names: the parameter names.
        intervals: one :class:`Interval` per name.
        owner: the model's class name, for messages.
    """

    names: tuple
    intervals: tuple
    owner: str = "model"

    @property
    def low(self) -> np.ndarray:
        """(p,) lower ends, -inf where open-ended."""
        return np.array([i.low for i in self.intervals], dtype=float)

    @property
    def high(self) -> np.ndarray:
        """(p,) upper ends, +inf where open-ended."""
        return np.array([i.high for i in self.intervals], dtype=float)

    def bounds(self, names=None) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) arrays for ``names`` (all the model's parameters when None): the box an
        optimiser keeps a fit in (whose map to an unconstrained coordinate treats every end as
        open)."""
        idx = range(len(self.names)) if names is None else [self.names.index(n) for n in names]
        return self.low[list(idx)], self.high[list(idx)]

    def inside(self, theta) -> np.ndarray:
        """Bool array of ``theta``'s shape ((p,) or (R, p)): each value in its domain (NaN is
        not)."""
        th = np.asarray(theta, dtype=float)
        lo_c = np.array([i.low_closed for i in self.intervals])
        hi_c = np.array([i.high_closed for i in self.intervals])
        above = np.where(lo_c, th >= self.low, th > self.low)
        below = np.where(hi_c, th <= self.high, th < self.high)
        return above & below

    def describe(self) -> str:
        """One line per parameter: name, domain, note."""
        return "\n".join(
            f"{n} in {i.text()}"
            + (f": {i.note.format(name=n, value='value', minus='-value')}" if i.note else "")
            for n, i in zip(self.names, self.intervals))


def gather(declared: dict, names, owner: str) -> ParamDomains | None:
    """The :class:`ParamDomains` of ``names`` from a mapping name -> :class:`Interval` (a
    class's ``PARAM_DOMAINS``); None when the mapping is empty. A name the mapping lacks is a
    programming error of the model (KeyError), not an open domain."""
    if not declared:
        return None
    return ParamDomains(tuple(names), tuple(declared[n] for n in names), owner)


def extended(domains: ParamDomains | None, names) -> ParamDomains | None:
    """``domains`` (a wrapped model's) with the parameters ``names`` appended, unbounded; None
    stays None."""
    if domains is None:
        return None
    names = tuple(names)
    return domains._replace(names=domains.names + names,
                            intervals=domains.intervals + (Interval(-math.inf, math.inf),) * len(names))


def envelope(declared: dict, names) -> np.ndarray | None:
    """(nx,) largest plausible magnitude per state (+inf where the mapping has none), from a
    mapping state name -> bound (a class's ``STATE_ENVELOPE``); None when the mapping is
    empty (finiteness only)."""
    if not declared:
        return None
    return np.array([float(declared.get(n, math.inf)) for n in names], dtype=float)


# -- the domains the built-in models share ---------------------------------------------------
#: a mass [kg]: positive (physical necessity; the equations divide by it)
MASS = interval("(0, inf)", "a mass is positive (the equations of motion divide by it)")
#: a moment of inertia [kg m^2]: positive (physical necessity)
INERTIA = interval("(0, inf)", "a moment of inertia is positive (the equations divide by it)")
#: the CoG's distance to an axle [m]: positive, the CoG between the axles
AXLE = interval(
    "(0, inf)", "the CoG lies between the axles, each distance positive (a physical "
    "necessity for the static axle loads m g lr / L and m g lf / L to be positive: a CoG "
    "outside the wheelbase tips the car over)")
#: a length of the car's geometry (track, CoG height, rolling radius) [m]
LENGTH = interval("(0, inf)", "a length of the car is positive")
#: a cornering stiffness [N/rad] in vehjax's (ISO 8855) sign convention
CORNERING = interval(
    "(0, inf)", "cornering stiffnesses are positive in vehjax's sign convention (ISO 8855: a "
    "positive slip angle gives a positive, leftward force). A stiffness in the SAE "
    "convention (y to the right: a positive slip angle gives a negative force, so the "
    "stiffness is negative) converts by a change of sign: {name} = {minus}")
#: a longitudinal slip stiffness [N per unit slip]
SLIP_STIFFNESS = interval(
    "(0, inf)", "a slip stiffness is positive (driving slip gives a driving force); a "
    "negative value is a sign-convention slip: {name} = {minus}")
#: a drag coefficient [N s^2/m^2]: non-negative (zero: no drag)
DRAG = interval("[0, inf)", "air drag opposes the motion: non-negative (0 means no drag)")
#: the friction coefficient [-]: positive, at most 3 (a convention of vehjax)
FRICTION = interval(
    "(0, 3)", "the friction coefficient (peak lateral force over the static load) is "
    "positive (a physical necessity: the tyre curves divide by the peak mu Fz). Its upper "
    "bound 3 is a convention of vehjax: road tyres on dry asphalt reach 0.9-1.3, racing "
    "slicks about 1.5-2, and 3 leaves room for moderate aerodynamic downforce, which the "
    "static loads of the model do not carry; a fit that wants more says the data do not "
    "saturate the tyres (use tyres='linear')")
#: Pacejka's shape factor C [-]
SHAPE = interval(
    "(0, 2)", "the magic formula's shape factor C lies in (0, 2): C > 0 is a necessity (B = "
    "c / (C D) divides by it); C < 2 keeps the force's sign that of the slip at every slip "
    "angle (beyond 2, sin(C arctan(B alpha)) turns negative at large slip); 1 < C < 2 gives a "
    "peak and a fall-off")

#: a body velocity [m/s] beyond any road vehicle (300 m/s is 1080 km/h)
SPEED_LIMIT = 300.0
#: a yaw, roll or wheel-free rate [rad/s] far beyond a car's (a car spinning at 20 rad/s turns
#: three times a second)
RATE_LIMIT = 20.0
#: a lateral axle force [N] beyond any road vehicle's (mu = 3 on a 34 t axle load)
FORCE_LIMIT = 1.0e6

#: a tyre's relaxation length [m]
RELAXATION = interval(
    "(0.01, 10)", "a relaxation length is positive (a physical necessity: the force's time "
    "constant sigma / vx divides by it). The bounds are vehjax's convention: car tyres have "
    "0.3-1.5 m and truck tyres up to about 2 m (of the order of the contact patch's length "
    "to a tyre's radius); 10 m leaves room for a lag that also takes up the steering's and "
    "the suspension's compliance. Below 0.01 m the time constant (0.5 ms at 20 m/s) is far "
    "below any sampling period: the lag is then neither identifiable nor worth its stiffness "
    "(use SingleTrack, the limit sigma -> 0)")
