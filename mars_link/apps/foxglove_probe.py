"""A minimal Foxglove WebSocket client: is the live view there, and how fast does it come?

    python -m mars_link.apps.foxglove_probe [ws://127.0.0.1:8765] [--seconds 5] [--topics /tf,/scene]

Subscribes (subprotocol foxglove.sdk.v1, the name foxglove-sdk's server gives Foxglove's WebSocket protocol,
the same messages as foxglove.websocket.v1) to the advertised topics and prints each topic's messages, rate
and simulated-time span. Used by the tests and benchmarks/bench_mcap.py; the `websockets` package.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import struct
import sys

from mars_link.processes.cli_options import add_foxglove_probe_options

SUBPROTOCOL = "foxglove.sdk.v1"


async def listen(url: str, topics: tuple[str, ...] | None, seconds: float) -> dict[str, list[tuple[float, int]]]:
    """topic -> [(arrival time on the loop's clock, message log time ns)] for `seconds` after subscribing;
    `topics` None: every advertised topic."""
    import websockets

    got: dict[str, list[tuple[float, int]]] = {t: [] for t in topics or ()}
    async with websockets.connect(url, subprotocols=[SUBPROTOCOL], max_size=None) as ws:
        if ws.subprotocol != SUBPROTOCOL:
            raise ConnectionError(f"{url}: the server speaks {ws.subprotocol!r}, not {SUBPROTOCOL}")
        subs: dict[int, str] = {}
        loop = asyncio.get_running_loop()
        end = None
        while end is None or loop.time() < end:
            try:
                frame = await asyncio.wait_for(ws.recv(), timeout=0.5)
            except asyncio.TimeoutError:
                continue
            except websockets.ConnectionClosed:  # the run ended: what came until then
                break
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") != "advertise":
                    continue
                wanted = [c for c in msg["channels"] if topics is None or c["topic"] in topics]
                new = []
                for ch in wanted:
                    sub = len(subs) + 1
                    subs[sub] = ch["topic"]
                    got.setdefault(ch["topic"], [])
                    new.append({"id": sub, "channelId": ch["id"]})
                if new:
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": new}))
                    end = end or loop.time() + seconds
            elif frame[0] == 0x01:  # message data: opcode, subscription id (u32), log time (u64 ns), payload
                sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
                if sub_id in subs:
                    got[subs[sub_id]].append((loop.time(), log_time))
    return got


def rates(got: dict[str, list[tuple[float, int]]]) -> dict[str, dict]:
    """Per topic: messages, rate (Hz of wall time) and the simulated time they span (s)."""
    out = {}
    for topic, msgs in got.items():
        span = msgs[-1][0] - msgs[0][0] if len(msgs) > 1 else 0.0
        out[topic] = {"messages": len(msgs), "rate_hz": (len(msgs) - 1) / span if span > 0 else 0.0,
                      "sim_span_s": (msgs[-1][1] - msgs[0][1]) / 1e9 if msgs else 0.0}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m mars_link.apps.foxglove_probe", description=__doc__.splitlines()[0])
    add_foxglove_probe_options(ap)
    a = ap.parse_args(argv)
    topics = tuple(a.topics.split(",")) if a.topics else None
    try:
        got = asyncio.run(listen(a.url, topics, a.seconds))
    except (OSError, ConnectionError) as exc:
        print(f"foxglove_probe: {a.url}: {exc}", file=sys.stderr)
        return 1
    for topic, r in sorted(rates(got).items()):
        print(f"{topic:12} {r['messages']:6d} msgs  {r['rate_hz']:6.1f} Hz  {r['sim_span_s']:7.2f} s simulated")
    return 0


if __name__ == "__main__":
    sys.exit(main())
