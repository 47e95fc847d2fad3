"""Captures saved as named arrays (MATLAB ``.mat``, NumPy ``.npz``): which variables are channels, and the rate.

A DAQ script saves its signals as variables beside a few scalars::

    save('capture.mat', 'dither', 'deflection', 'fs')        % MATLAB
    np.savez('capture.npz', dither=d, deflection=x, fs=5e5)   # NumPy

Without ``--channel``, every numeric vector (one dimension longer than 1) is a
channel named after its variable, except a time vector (``t``, ``time``); they
must share one length.  ``--channel deflection=NAME`` maps a variable to a
channel (only the mapped ones are read), and ``--channel deflection=NAME:K``
column ``K`` (from 0) of a matrix whose longer dimension is the samples.

The sample rate is ``--sample-rate``, else a numeric scalar variable:
``fs``, ``Fs``, ``FS``, ``sample_rate``, ``sample_rate_hz``, ``sampling_rate``,
``SampleRate`` (Hz), or ``dt``, ``Ts``, ``sample_interval`` (s).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import NamedTuple

from afmtool.errors import InputError

__all__ = ["Variable", "ChannelSource", "choose_channels", "RATE_NAMES", "INTERVAL_NAMES", "rate_variable"]

#: Scalar variables that give the sample rate in Hz, in order of preference.
RATE_NAMES = ("fs", "Fs", "FS", "sample_rate", "sample_rate_hz", "sampling_rate", "SampleRate", "samplerate")
#: Scalar variables that give the sample interval in s.
INTERVAL_NAMES = ("dt", "Ts", "sample_interval", "sampling_interval")
#: Vectors that are the time axis, not a signal.
_TIME_NAMES = frozenset({"t", "time", "times", "t_s", "time_s"})
#: Most variables a file may list (each is a small header).
MAX_VARIABLES = 100_000


class Variable(NamedTuple):
    """A variable's name, its shape as (samples, columns) where it is numeric and at most 2-D, and its kind.

    ``n_samples`` and ``n_columns`` are ``None`` for a variable that is not a numeric
    vector or matrix (text, a cell, a struct, a 3-D array); ``kind`` says what it holds.
    """

    name: str
    n_samples: int | None
    n_columns: int | None
    kind: str
    units: str = ""

    @property
    def numeric(self) -> bool:
        return self.n_samples is not None


class ChannelSource(NamedTuple):
    """Where a channel's samples are: a variable and, for a matrix, its column."""

    variable: str
    column: int


def _mapped(path, variables: Mapping[str, Variable], channel: str, source: str) -> ChannelSource:
    name, sep, column_text = source.rpartition(":") if ":" in source else (source, "", "")
    variable = variables.get(name)
    if variable is None:
        listed = ", ".join(list(variables)[:20]) or "none"
        raise InputError(f"{path}: --channel {channel}={source}: no variable {name!r} (has: {listed})")
    if not variable.numeric:
        raise InputError(f"{path}: variable {name!r} holds {variable.kind}, not numbers; it cannot be a channel")
    if not sep:
        if variable.n_columns != 1:
            raise InputError(f"{path}: variable {name!r} is a {variable.n_samples} x {variable.n_columns} matrix; "
                             f"choose a column: --channel {channel}={name}:0")
        return ChannelSource(name, 0)
    if not column_text.strip().isdigit() or int(column_text) >= variable.n_columns:
        raise InputError(f"{path}: --channel {channel}={source}: {name!r} has columns 0..{variable.n_columns - 1}")
    return ChannelSource(name, int(column_text))


def choose_channels(path, variables: Mapping[str, Variable], channel_map: Mapping[str, str] | None) -> dict[str, ChannelSource]:
    """The channels to read, by channel name, checked to share one length (see the module docstring).

    Raises
    ------
    InputError
        A mapped variable that is missing, not numeric, or a matrix without a column; no
        vectors at all; or channels of different lengths.
    """
    if len(variables) > MAX_VARIABLES:
        raise InputError(f"{path}: {len(variables)} variables; afmtool reads files of at most {MAX_VARIABLES}")
    if channel_map:
        chosen = {channel: _mapped(path, variables, channel, source) for channel, source in channel_map.items()}
    else:
        chosen = {v.name: ChannelSource(v.name, 0) for v in variables.values()
                  if v.numeric and v.n_columns == 1 and v.n_samples > 1 and v.name not in _TIME_NAMES}
        if not chosen:
            matrices = [v.name for v in variables.values() if v.numeric and v.n_columns > 1]
            hint = f"; map a matrix's columns with --channel deflection={matrices[0]}:0" if matrices else ""
            raise InputError(f"{path}: no numeric vector to read as a channel (variables: "
                             f"{', '.join(list(variables)[:20]) or 'none'}){hint}")
    lengths = {channel: variables[source.variable].n_samples for channel, source in chosen.items()}
    if len(set(lengths.values())) > 1:
        listed = ", ".join(f"{channel} {n}" for channel, n in lengths.items())
        raise InputError(f"{path}: arrays of different lengths ({listed}); choose those of one capture with "
                         "--channel NAME=VARIABLE")
    return chosen


def rate_variable(path, values: Mapping[str, float | None]) -> float | None:
    """The sample rate from ``{variable name: its scalar value}`` (None where it is not one number).

    Raises
    ------
    InputError
        A rate variable that is present but not a finite positive number.
    """
    for names, invert in ((RATE_NAMES, False), (INTERVAL_NAMES, True)):
        for name in names:
            if name in values:
                value = values[name]
                if value is None or not (math.isfinite(value) and value > 0):
                    raise InputError(f"{path}: variable {name} = {value!r} is not a positive number (the sample "
                                     f"{'interval' if invert else 'rate'}); give --sample-rate")
                return 1.0 / value if invert else value
    return None
