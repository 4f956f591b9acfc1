"""Run one rolling cycle (on the egg, in simulation), watch it live, and save it.

With a service running (`sdh2svc serve --sim`, or on a real hand):
`python examples/client_example.py [http://127.0.0.1:8000] [--token TOKEN]`.
"""

from __future__ import annotations

import argparse
import asyncio

from sdh2svc.client import AsyncClient, Conflict


async def main(url: str, token: str | None) -> None:
    async with AsyncClient(url, token=token) as hand:
        status = await hand.status()
        obj = "egg" if status["sim"] else None  # a real hand holds what it is given
        async with hand.telemetry(tactile=False, decimate=10) as live:
            try:
                run_id = (await hand.start_run({"cycles": 1}, object=obj))["run_id"]
            except Conflict as e:  # a run is running, or the e-stop is latched
                raise SystemExit(e.error) from None
            async for msg in live:
                if msg["type"] == "sample" and msg["run_id"] == run_id:
                    s = msg["sample"]
                    print(f"t = {s['t']:6.2f} s  F = {_num(s['F'])}  σ = {_num(s['sigma'])}°")
                elif msg["type"] == "event" and msg["run_id"] == run_id:
                    print("event:", msg["kind"], msg["detail"])
                    if msg["kind"] == "end":
                        break
        end = await hand.wait_run(run_id)
        print(f"run {run_id}: {end['status']}, {(await hand.run(run_id))['iterations']} iterations")
        print("saved", await hand.export(run_id, f"run-{run_id}.mcap"))  # opens in Foxglove
        print("saved", await hand.export(run_id, f"run-{run_id}.csv"))


def _num(value: float | None) -> str:
    return "–" if value is None else f"{value:5.2f}"  # a field is null where it does not exist


if __name__ == "__main__":
    args = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    args.add_argument("url", nargs="?", default="http://127.0.0.1:8000")
    args.add_argument("--token", help="the service's token, if it has one")
    ns = args.parse_args()
    asyncio.run(main(ns.url, ns.token))
