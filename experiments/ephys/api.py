"""The Python API of virtual electrophysiology: :func:`run` a protocol, get an :class:`xarray.Dataset`;
:func:`to_nwb` shares it as Neurodata Without Borders.

``run`` is ``lobula ephys`` as a function. Its keyword options are the command line's options
(``--neuron-model`` is ``neuron_model``) or the protocol function's own keyword names
(``temporal_frequencies_hz`` for ``--tf``, ``l_over_v_s`` for ``--l-over-v``); they are turned into
that command line and parsed by the very parser of ``lobula ephys``, so a value is checked, an
option refused for a protocol it does not apply to, and a protocol added to
:data:`experiments.ephys.command.PROTOCOLS` is run, exactly as on the command line. It lives in
:mod:`experiments.ephys` because it drives stimuli (:mod:`stimuli`) through the model
(:mod:`lobula`), which imports neither.
"""
from __future__ import annotations

import argparse
import difflib
from pathlib import Path

__all__ = ["run", "to_nwb", "options", "command_argv"]

#: Python keyword -> ``lobula ephys`` option dest, for the keywords not found in the protocols' own table
#: (:data:`experiments.ephys.command._STIMULUS_OPTIONS`): the rig's options with their units
_ALIASES = {"tau_s": "tau", "dphi_deg": "dphi", "field_size_deg": "field_size", "contrasts": "contrast"}
#: command-line dests that are not recording options (outputs and the figure are run's own keywords)
_NOT_OPTIONS = {"protocol", "out", "plot", "quiet", "func", "command", "experimenter", "institution", "eye"}


class _Refuse(argparse.ArgumentParser):
    """An argparse parser whose errors raise :class:`ValueError` (a Python caller gets an exception,
    not a process exit)."""

    def error(self, message):
        raise ValueError(message)


def _parser() -> argparse.ArgumentParser:
    """The ``ephys`` subparser of ``lobula``, raising ValueError on a bad value."""
    from .command import add_parser

    top = _Refuse(prog="lobula")
    sub = top.add_subparsers(dest="command", parser_class=_Refuse)
    add_parser(sub)
    return sub.choices["ephys"]


def _actions() -> dict:
    """{dest: argparse action} of every recording option of ``lobula ephys``."""
    return {a.dest: a for a in _parser()._actions if a.option_strings and a.dest not in _NOT_OPTIONS
            and a.dest != "help"}


def _aliases(protocol: str) -> dict:
    """{Python keyword: option dest} for ``protocol``: the protocol function's keyword names and the rig's."""
    from .command import _STIMULUS_OPTIONS

    out = dict(_ALIASES)
    out.update({kw: dest for dest, kw in _STIMULUS_OPTIONS.get(protocol, ()) if kw != dest})
    return out


def options(protocol: str | None = None) -> dict:
    """The keyword options of :func:`run` and their help (the command line's, with its default).

    Parameters
    ----------
    protocol : str, optional
        Only the options that apply to this protocol (default: every option).

    Returns
    -------
    dict
        {keyword: help text}; each keyword is the dest of a ``lobula ephys`` option.
    """
    from .command import APPLIES, PROTOCOLS

    if protocol is not None and protocol not in PROTOCOLS:
        raise ValueError(f"unknown protocol {protocol!r}; use one of {', '.join(PROTOCOLS)}")
    return {d: a.help for d, a in _actions().items()
            if protocol is None or protocol in APPLIES.get(d, PROTOCOLS)}


def _words(value) -> list[str]:
    """A Python value as command-line words: a list or array gives one word per element."""
    if isinstance(value, (str, Path)) or not hasattr(value, "__iter__"):
        value = [value]
    words = []
    for v in value:
        if isinstance(v, bool):
            raise ValueError(f"{v!r} is not a value of this option (booleans are not)")
        words.append(repr(float(v)) if isinstance(v, float) else str(v.item() if hasattr(v, "item") else v))
    return words


def command_argv(protocol: str, circuit: str = "pinhole", out=None, **opts) -> list[str]:
    """The ``lobula ephys`` command line (arguments after ``lobula``) equivalent to ``run(protocol, circuit,
    out=out, **opts)``; raises ValueError for an unknown circuit or option, naming the fix.

    Parameters
    ----------
    protocol : str
        One of :data:`experiments.ephys.command.PROTOCOLS`.
    circuit : {"pinhole", "fly"}
        The eye recorded (``--eye``).
    out : str, Path or list of them, optional
        Output files (.nc, .nwb).
    **opts
        Keyword options, as :func:`run` takes them.

    Returns
    -------
    list of str
        ``["ephys", protocol, "--opt", "value", …]``.
    """
    from .command import APPLIES, PROTOCOLS

    if protocol not in PROTOCOLS:
        near = difflib.get_close_matches(str(protocol), PROTOCOLS, n=1)
        raise ValueError(f"unknown protocol {protocol!r}" + (f" (did you mean {near[0]!r}?)" if near else "")
                         + f"; use one of {', '.join(PROTOCOLS)}")
    if circuit not in ("pinhole", "fly"):
        raise ValueError(f"circuit must be 'pinhole' (the camera's lattice and its LC population) or 'fly' (the "
                         f"compound eyes' circuit), got {circuit!r}")
    actions, aliases = _actions(), _aliases(protocol)
    argv = ["ephys", protocol]
    if circuit == "fly":
        if protocol not in APPLIES["eye"]:
            raise ValueError(f"circuit='fly' does not apply to {protocol}; the compound eye runs "
                             f"{', '.join(APPLIES['eye'])} (use circuit='pinhole')")
        argv += ["--eye", "fly"]
    for key, value in opts.items():
        dest = aliases.get(key, key)
        if dest not in actions:
            near = difflib.get_close_matches(key, list(actions) + list(aliases), n=3)
            raise ValueError(f"unknown option {key}=" + (f"; did you mean {' or '.join(near)}?" if near else "")
                             + f" {protocol}'s options: {', '.join(options(protocol))} "
                             f"(experiments.ephys.options({protocol!r}) gives their help)")
        if protocol not in APPLIES.get(dest, PROTOCOLS):
            raise ValueError(f"{key}= does not apply to {protocol}; it applies to {', '.join(APPLIES[dest])} "
                             f"(drop it, or run one of those)")
        if value is None:
            continue  # the protocol's own default
        argv += [actions[dest].option_strings[0], *_words(value)]
    if out is not None:
        argv += ["--out", *_words(out)]
    return argv


def run(protocol: str, circuit: str = "pinhole", *, out=None, progress: bool = False, **options):
    """Run a virtual-electrophysiology protocol on the model fly and return the labelled recording.

    The same run as ``lobula ephys PROTOCOL …`` (:mod:`experiments.ephys.command`): the options are
    parsed and checked by that command's parser, so every protocol it lists runs here too.

    Parameters
    ----------
    protocol : str
        ``"tf-tuning"`` (drifting gratings over temporal frequency; known answer: the EMD optimum
        1/(2πτ)), ``"rf-map"`` (local-motion spot mapping of the LC fields), ``"looming"`` (a disc
        approaching or receding over l/|v|; time relative to collision), ``"velocity-replay"``
        (the readout neuron on a run's footage), ``"edges"`` (ON/OFF edges through T4/T5 to HS/VS),
        or any other protocol of :data:`experiments.ephys.command.PROTOCOLS`.
    circuit : {"pinhole", "fly"}, default "pinhole"
        The eye recorded: the pinhole lattice over the D435i's field of view with its LC
        population, or the fly's two compound eyes with the circuit `lobula eye-velocity` uses
        (``--eye fly``; not for ``edges``).
    out : str, Path or list of them, optional
        Also write the recording there, by suffix: ``.nc`` (NetCDF, CF-1.10) and/or ``.nwb``.
    progress : bool, default False
        Progress bars where a protocol runs long (velocity-replay).
    **options
        The command line's options by their Python names, a list for the options that take
        several values (a scalar is one value). The main ones, with their defaults:

        - every protocol: ``record`` (list of monitors, e.g. ``["lc.rate", "lc.spikes[expansion]",
          "emd.response[0:10]", "t4.response[front-to-back]", "hs.v"]``; default: the protocol's),
          ``tau`` or ``tau_s`` (EMD delay, s; 0.035), ``dphi`` or ``dphi_deg`` (interommatidial
          angle, degree; 2), ``field_size`` or ``field_size_deg`` (LC field size, degree; 10);
        - neurons (tf-tuning, looming, velocity-replay, edges): ``neuron_model`` ("rate",
          "poisson", "lif"; "rate"), ``trials`` (4 for spiking models, 1 for rate), ``seed`` (0);
        - tf-tuning: ``temporal_frequencies_hz`` or ``tf`` (Hz; 16 log-spaced 0.5–32),
          ``contrast`` or ``contrasts`` (0.5), ``duration`` or ``duration_s`` (2 s),
          ``baseline`` or ``baseline_s`` (mean-luminance period before onset, s; 0.3),
          ``wavelength`` (degree; 20), ``stimulus`` ("rings" or "grating"), ``settle`` (s; 0.5),
          ``direction`` (degree; grating only);
        - rf-map: ``fields``, ``directions`` (4), ``spacing``, ``extent``, ``spot_size``,
          ``spot_path``, ``spot_speed`` (degree, degree/s; multiples of Δφ);
        - looming: ``l_over_v`` or ``l_over_v_s`` (s; 0.01 0.02 0.04 0.08), ``duration`` (1 s),
          ``collision_time`` (s; 0.8 × duration), ``baseline_s`` (s; 0.3), ``max_size`` (degree; 60),
          ``contrast`` (1);
        - edges: ``speed`` (degree/s; 50), ``bar_width`` (degree; edges), ``contrast`` (0.5),
          ``duration``;
        - velocity-replay: ``footage``, ``duration`` (10 s), ``rotation``, ``haltere_gain``
          (circuit "fly").

        :func:`options` lists every option of a protocol with its help and default.

    Returns
    -------
    xarray.Dataset
        The recording: dims ``trial``, ``time`` (s), the recorded populations' dims and one dim per
        stimulus parameter, CF-1.10 attributes; ``attrs["command_line"]`` is the equivalent
        ``lobula ephys`` command.

    Raises
    ------
    ValueError
        An unknown protocol or option (with the closest names), an option that does not apply to
        the protocol (with the protocols it applies to), or a value out of range.

    Examples
    --------
    >>> ds = run("tf-tuning", temporal_frequencies_hz=[1, 4, 16], neuron_model="poisson", trials=3,
    ...          record=["lc.rate", "lc.spikes"])                                  # doctest: +SKIP
    >>> ds.lc_spikes_tuning.sel(contrast=0.5)                                      # doctest: +SKIP
    """
    from lobula.version import command_line

    from .command import check_outputs, given, run_protocol, write_outputs

    argv = command_argv(protocol, circuit, out, **options)
    # The placeholder output satisfies the parser's required --out; the outputs are written below.
    args = _parser().parse_args(argv[1:] + ([] if out is not None else ["--out", "unused.nc"]))
    outs = check_outputs(args.out) if out is not None else []
    ds = run_protocol(protocol, given(args), progress=progress)
    cmd = command_line(["lobula", *argv])
    ds.attrs["command_line"] = cmd
    ds.attrs["history"] = f"{ds.attrs.get('created', '')} {cmd} (experiments.ephys.run)".strip()
    for _ in write_outputs(ds, outs):
        pass
    return ds


def to_nwb(ds, path, **metadata) -> Path:
    """Write a recording of :func:`run` as a Neurodata Without Borders file, atomically.

    Parameters
    ----------
    ds : xarray.Dataset
        A recording of any protocol (:func:`run`, or a NetCDF file opened with xarray).
    path : str or Path
        The ``.nwb`` file.
    **metadata
        ``experimenter`` ("Last, First", one or a list), ``institution``, ``lab``.

    Returns
    -------
    Path
        ``path``. The layout is :mod:`experiments.nwb`'s.
    """
    from experiments.nwb import write_nwb

    return write_nwb(ds, path, **metadata)


