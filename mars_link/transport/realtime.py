"""Command age at the motor, measured from the raw MAVLink bytes a unit receives.

In real-time mode (the world paced to the wall clock, `--speed 1`) sim time t is wall time epoch + t.
A unit estimates the epoch from its HIL link as min over steps of (sensor arrival wall time - t): the
world sends step k no earlier than epoch + t_k, so the minimum is the epoch plus the smallest one-way
delay (tens of microseconds on loopback; it makes the ages slightly optimistic by that much). A per-rotor
command (SET_ACTUATOR_CONTROL_TARGET) is stamped with the sim time t of the sensor data it was computed
from; its age at the motor is the wall time the unit drives its motors with it (its HIL_ACTUATOR_CONTROLS
for t leaves for the simulator) - (epoch + t). The logs also keep when the unit read the command. Ages
beyond one control period mean the 100 Hz deadline was missed.
"""

from __future__ import annotations

import os
import struct
import time
from pathlib import Path

import numpy as np

from mars_link.logs.outputs import write_json
from mars_link.mavlink.codec import frame_length, frame_message_id, header_length
from mars_link.transport.base import TappedTransport, Transport

CPU_DMA_LATENCY = "/dev/cpu_dma_latency"
MSG_HIL_SENSOR = 107
MSG_SET_ACTUATOR_CONTROL_TARGET = 139
MSG_HIL_ACTUATOR_CONTROLS = 93
_U64 = struct.Struct("<Q")


def percentiles_ms(values_s) -> dict:
    a = np.asarray(values_s, dtype=float) * 1e3
    if a.size == 0:
        return {"n": 0}
    return {"n": int(a.size), "p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()), "mean_ms": float(a.mean())}


def frame_times_usec(data: bytes, msgid: int) -> list[int]:
    """time_usec (the first field, uint64) of every frame of `msgid` in a datagram; tolerant of junk."""
    out = []
    i, n = 0, len(data)
    while i + 8 <= n:
        total = frame_length(data, i)
        if total is None:
            i += 1
            continue
        if frame_message_id(data, i) == msgid and i + total <= n:
            start, plen = i + header_length(data, i), data[i + 1]
            payload = data[start:start + plen] + bytes(max(0, 8 - plen))  # MAVLink 2 trims trailing zeros
            out.append(_U64.unpack_from(payload)[0])
        i += total
    return out


class CommandAgeTap:
    """Unit side: shown the datagrams of the unit's HIL and coordinator links (`hil_link`,
    `coordinator_link` wrap them); logs the command ages and when each step's sensor datagram was read
    (the first stage of the path)."""

    def __init__(self, unit_id: int, control_period_s: float = 0.01) -> None:
        self.unit_id = unit_id
        self.control_period_s = control_period_s
        self.offset_s = float("inf")  # epoch estimate: min(sensor arrival - t)
        self.commands: dict[float, float] = {}  # t_s -> wall time the unit read the command for t
        self.motor_outputs: list[tuple[float, float]] = []  # (t_s, wall time the motors got it)
        self.sensors: dict[float, float] = {}  # t_s -> arrival wall time of its sensor datagram

    def hil_link(self, link: Transport) -> Transport:
        """The unit's HIL link, tapped: sensor datagrams in (the epoch), motor outputs out."""
        return TappedTransport(link, self.on_hil, self.on_motor_output)

    def coordinator_link(self, link: Transport) -> Transport:
        """The unit's coordinator link, tapped: rotor commands in."""
        return TappedTransport(link, self.on_coordinator)

    def on_hil(self, data: bytes, now_s: float | None = None) -> None:
        now_s = time.time() if now_s is None else now_s
        for t_us in frame_times_usec(data, MSG_HIL_SENSOR):
            self.offset_s = min(self.offset_s, now_s - t_us / 1e6)
            self.sensors.setdefault(t_us / 1e6, now_s)

    def on_coordinator(self, data: bytes, now_s: float | None = None) -> None:
        now_s = time.time() if now_s is None else now_s
        for t_us in frame_times_usec(data, MSG_SET_ACTUATOR_CONTROL_TARGET):
            self.commands.setdefault(t_us / 1e6, now_s)

    def on_command(self, t_s: float, now_s: float | None = None) -> None:
        """A per-rotor command for sim time `t_s` read from another interface (PX4's ActuatorMotors)."""
        self.commands.setdefault(t_s, time.time() if now_s is None else now_s)

    def on_motor_output(self, data: bytes, now_s: float | None = None) -> None:
        """A datagram the unit sent to the simulator: its motor outputs for the steps it names."""
        now_s = time.time() if now_s is None else now_s
        for t_us in frame_times_usec(data, MSG_HIL_ACTUATOR_CONTROLS):
            if t_us / 1e6 in self.commands:  # driven with a coordinator command (not a fail-safe)
                self.motor_outputs.append((t_us / 1e6, now_s))

    def ages_s(self) -> list[tuple[float, float]]:
        """(t, age at the motor) of every step whose motors were driven with a coordinator command."""
        return [(t, out - (self.offset_s + t)) for t, out in self.motor_outputs]

    def summary(self) -> dict:
        ages = [a for _, a in self.ages_s()]
        stats = percentiles_ms(ages)
        stats["deadline_misses"] = int(sum(a > self.control_period_s for a in ages))
        stats["epoch_s"] = self.offset_s  # wall time of sim time 0 (as this unit estimates it)
        return stats

    def write(self, out: Path) -> dict:
        """command_age_unit<i>.csv (t_s, then since the sample time: sensors_in_s when the unit read
        the step's sensors, command_in_s its command, age_s its motors driven with it) and
        command_age_unit<i>.json (percentiles of age_s, misses, epoch)."""
        out.mkdir(parents=True, exist_ok=True)

        def since(wall: float | None, t: float) -> str:
            return "" if wall is None else f"{wall - (self.offset_s + t):.6f}"

        from mars_link.logs.outputs import SafeWriter

        # through the safe writer: a full disk stops this log (its reason in the .json), never the unit's end
        f = SafeWriter.open(out / f"command_age_unit{self.unit_id}.csv")
        f.write("t_s,sensors_in_s,command_in_s,age_s\n")
        for t, age in self.ages_s():
            if not f.active:
                break
            f.write(f"{t:.6f},{since(self.sensors.get(t), t)},{since(self.commands.get(t), t)},{age:.6f}\n")
        f.close()
        stats = self.summary()
        if f.stopped_reason:
            stats["logging_stopped"] = f.stopped_reason
        try:
            write_json(out / f"command_age_unit{self.unit_id}.json", stats)  # strict JSON: NaN -> null
        except OSError:
            pass  # (the figures are in the unit's status too; the summary says the log stopped)
        return stats


class CpuWakeLatency:
    """Keep idle CPUs out of their deep idle states while a real-time run lasts (Linux PM QoS: what
    cyclictest and real-time audio do). A CPU woken from a halt (on a VM: a halted vCPU the host must
    reschedule) takes up to milliseconds to run the process a datagram was sent to; every hop of the
    lockstep pays it. Writing 0 to /dev/cpu_dma_latency asks for 0 us of wake-up latency until the
    file is closed; it needs write access (root, or a udev rule granting it). `state` says what held."""

    def __init__(self, path: str = CPU_DMA_LATENCY) -> None:
        self._fd: int | None = None
        try:
            self._fd = os.open(path, os.O_WRONLY)
            os.write(self._fd, struct.pack("<i", 0))
            self.state = "held at 0 us"
        except OSError as e:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None
            self.state = f"not held ({path}: {e.strerror or e})"

    @property
    def held(self) -> bool:
        return self._fd is not None

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
