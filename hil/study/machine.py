"""The study's machine as text that travels to any Dask worker, rebuilt there per sample.

A worker of a remote cluster need not see the files the study names, so the client reads
the machine file (or the manifest and each axis's file) once, checks it with the project's
own loader (:func:`plant.machines.load_machine_set`), and sends the text.  A worker
applies one sample's keys on top of each file, as a manifest's ``[axis.overrides]`` and
:func:`plant.config.load_machine`'s ``overrides`` do (the sample's value wins over the
manifest's), and checks the result with :func:`plant.config.parse_machine`: a sample the
machine-file rules refuse is refused the same way.
"""

import copy
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import tomllib

from plant.config import MAX_FILE_BYTES, MachineConfig, parse_machine, read_toml
from plant.files import read_text
from plant.machines import Axis, MachineSet, load_machine_set


@dataclass(frozen=True)
class AxisSource:
    """One axis: its letter, its machine file's path (for messages) and text, and the
    manifest's overrides of it (``{section: {key: value}}``)."""
    name: str
    path: str
    text: str
    overrides: dict

    @cached_property
    def document(self) -> dict:
        """``text`` parsed, once per process: a study builds its machine once per sample,
        and parsing the text takes ten times as long as copying the parsed document."""
        return tomllib.loads(self.text)


@dataclass(frozen=True)
class MachineSource:
    """A machine (one machine file, or a manifest) as text.

    Attributes:
        path: the machine file or manifest as named by the study.
        name, source: the machine's name and where it comes from.
        manifest: read from a manifest (parameters are then ``AXIS.section.key``).
        axes: the axes in order.
    """
    path: str
    name: str
    source: str
    manifest: bool
    axes: tuple[AxisSource, ...]

    @property
    def letters(self) -> tuple[str, ...]:
        """The axis letters in order."""
        return tuple(a.name for a in self.axes)

    def build(self, overrides: dict[str, dict[str, dict]] | None = None) -> MachineSet:
        """The machine with ``overrides`` (``{axis: {section: {key: value}}}``, axis "" on
        a machine file) applied; ConfigError as the machine-file loader words it."""
        overrides = overrides or {}
        axes = []
        for a in self.axes:
            raw = copy.deepcopy(a.document)
            for changes in (a.overrides, overrides.get("" if not self.manifest else a.name, {})):
                for sec, values in changes.items():
                    raw.setdefault(sec, {}).update(copy.deepcopy(values))
            axes.append(Axis(a.name, parse_machine(raw, a.path)))
        return MachineSet(self.path, self.name, self.source, tuple(axes), self.manifest)

    def configs(self) -> dict[str, MachineConfig]:
        """Axis letter ("" on a machine file) -> its machine file as written."""
        machine = self.build()
        if not self.manifest:
            return {"": machine.axes[0].config}
        return {a.name: a.config for a in machine.axes}


def _text(path: Path) -> str:
    """A machine file's text, read as its loader reads it (:func:`plant.files.read_text`)."""
    return read_text(path, "machine file", MAX_FILE_BYTES)


def read_machine(path: Path) -> MachineSource:
    """Check ``path`` (machine file or manifest) with the project's loader and read its
    text; ConfigError as the loader words it."""
    machine = load_machine_set(path)
    if not machine.manifest:
        axis = machine.axes[0]
        return MachineSource(str(path), machine.name, machine.source, False,
                             (AxisSource(axis.name, str(path), _text(path), {}),))
    entries = read_toml(path)["axis"]
    axes = []
    for entry, axis in zip(entries, machine.axes, strict=True):
        file = (path.parent / entry["file"]).resolve()
        axes.append(AxisSource(axis.name, str(file), _text(file),
                               copy.deepcopy(entry.get("overrides", {}))))
    return MachineSource(str(path), machine.name, machine.source, True, tuple(axes))

