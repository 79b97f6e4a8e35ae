"""Localisation error: the pose each role believes it has (docs/COMMS.md, "Localisation error").

A :class:`PoseErrorProfile` gives each role a horizontal position error made of three parts, each
per axis (east, north) and in metres, plus an optional heading error:

* ``bias_m``: the standard deviation of a constant offset drawn once per episode;
* ``drift_m``: the stationary standard deviation of a first-order Gauss-Markov walk with correlation
  time ``drift_tau_s``: a random walk pulled back towards zero, so it wanders for minutes but never
  runs away (the usual model of GNSS's slowly varying error);
* ``noise_m``: white noise drawn at every fix;
* ``yaw_noise_deg``: white heading noise at every fix.

Inside the *degraded zone* (buildings crowding the sky, decided by the world from the town's own
geometry: world/sim/localisation.py) the drift and the noise are multiplied by ``urban_factor``.

:class:`PoseErrors` draws the fixes of one episode. Each role has its own random stream, derived
from the episode seed and the link seed; every fix draws the same five numbers whatever the
profile, and a role asked twice at one instant gets the same fix, so the same seed gives the same
errors in one process or many.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from agos.runtime.keys import ROLES
from agos.runtime.textfiles import read_profile

PROFILE_DIR = Path(__file__).resolve().parents[1] / "deploy" / "sensing"


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RoleError(_Section):
    """One role's error model (metres per axis; see the module)."""

    bias_m: float = Field(0.0, ge=0)
    drift_m: float = Field(0.0, ge=0)
    drift_tau_s: float = Field(60.0, gt=0)
    noise_m: float = Field(0.0, ge=0)
    yaw_noise_deg: float = Field(0.0, ge=0)
    urban_factor: float = Field(1.0, ge=1)
    """Multiplies ``drift_m`` and ``noise_m`` inside the degraded zone."""

    @property
    def exact(self) -> bool:
        return self.bias_m == self.drift_m == self.noise_m == self.yaw_noise_deg == 0


class PoseErrorProfile(_Section):
    """A localisation-error profile (``deploy/sensing/<name>.toml``)."""

    name: str
    description: str = ""
    uav: RoleError = RoleError()
    ugv: RoleError = RoleError()

    @property
    def exact(self) -> bool:
        return self.uav.exact and self.ugv.exact

    def of(self, role: str) -> RoleError:
        return self.uav if role == "uav" else self.ugv


EXACT = PoseErrorProfile(name="exact")
"""No error: the paper's setting and the default (``deploy/sensing/exact.toml`` is the same profile)."""


class PoseErrorProfileError(ValueError):
    """A bad pose-error profile; the message names the file and the field."""


def load_pose_error(name_or_path: str | Path) -> PoseErrorProfile:
    """A profile by name (``deploy/sensing/<name>.toml``) or file path; :class:`PoseErrorProfileError`
    (one line) for a missing, unreadable or invalid one."""
    return read_profile(name_or_path, PROFILE_DIR, PoseErrorProfile, PoseErrorProfileError, what="pose-error profile",
                        known_as="known profiles")


@dataclass(frozen=True)
class Fix:
    """The error of one fix: what to add to the true pose to get the believed one."""

    dx_m: float
    dy_m: float
    dyaw_rad: float
    degraded: bool

    @property
    def horizontal_m(self) -> float:
        return math.hypot(self.dx_m, self.dy_m)


NO_ERROR = Fix(0.0, 0.0, 0.0, False)


class _RoleStream:
    def __init__(self, spec: RoleError, rng: np.random.Generator) -> None:
        self.spec, self.rng = spec, rng
        self.bias = rng.standard_normal(2) * spec.bias_m
        self.walk = rng.standard_normal(2)  # in units of drift_m: starts in its stationary distribution
        self.t_s: float | None = None
        self.last = NO_ERROR

    def fix(self, t_s: float, crowded: Callable[[], bool]) -> Fix:
        if self.t_s is not None and t_s == self.t_s:
            return self.last
        degraded = self.spec.urban_factor != 1 and (self.spec.drift_m > 0 or self.spec.noise_m > 0) and crowded()
        z = self.rng.standard_normal(5)  # always five draws: the stream never depends on the profile's values
        dt = 0.0 if self.t_s is None else max(0.0, t_s - self.t_s)
        keep = math.exp(-dt / self.spec.drift_tau_s)
        self.walk = self.walk * keep + math.sqrt(1.0 - keep * keep) * z[:2]
        factor = self.spec.urban_factor if degraded else 1.0
        d = self.bias + factor * (self.spec.drift_m * self.walk + self.spec.noise_m * z[2:4])
        self.t_s = t_s
        self.last = Fix(float(d[0]), float(d[1]), math.radians(self.spec.yaw_noise_deg) * float(z[4]), degraded)
        return self.last


class PoseErrors:
    """The fixes of one episode, per role, in simulated time (non-decreasing per role)."""

    def __init__(self, profile: PoseErrorProfile, seed: int) -> None:
        self.profile = profile
        streams = np.random.SeedSequence([seed, 0x706F7365]).spawn(2)  # "pose": apart from the link streams
        self._roles: dict[str, _RoleStream] = {role: _RoleStream(profile.of(role), np.random.default_rng(s))
                                               for role, s in zip(ROLES, streams, strict=True)}

    def fix(self, role: str, t_s: float, crowded: Callable[[], bool] = lambda: False) -> Fix:
        """The role's error at ``t_s``; the same fix for a second call at the same instant. ``crowded``
        says whether the role is in the degraded zone now; it is asked only when that changes the fix."""
        if self.profile.of(role).exact:
            return NO_ERROR
        return self._roles[role].fix(t_s, crowded)
