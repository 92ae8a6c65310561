"""Training throughput on 1 vs N devices (`TrainConfig.devices`, `sgjax train --devices N`); run by hand,
prints a markdown table.

    python -m benchmarks.bench_train_devices [--model light|tiny] [--devices 2] [--steps 30] [--rounds 2]

Each measurement is a fresh interpreter started with XLA_FLAGS=--xla_force_host_platform_device_count=N
(the host split into N CPU devices), so both settings run in the same kind of process and differ only in
the data-parallel width; the settings alternate (1, N, 1, N, ...) so that a change in the machine's load
hits both. A measurement: E-RNet's jitted train step (`train.trainer.make_steps`) placed as `run_training`
places it (`trainer.Placement`: state replicated, batches split along "data"), on synthetic batches
already on the devices (the loader thread is left out), `--steps` steps after compiling and two warm-up
steps. On a shared CPU the absolute numbers move with other jobs: compare the ratio.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time


def measure(model: str, devices: int, steps: int, batch_size: int) -> dict:
    """One setting in this process -> {"samples_per_s", "compile_s", "devices_seen"}."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from flax import nnx

    from sgjax.stage2.ernet import ERNet, ERNetConfig
    from train import dataset, trainer

    model_config = {"light": ERNetConfig.light, "tiny": ERNetConfig.tiny}[model]()
    config = trainer.TrainConfig(batch_size=batch_size, model=model_config, devices=devices)
    placement = trainer.Placement.for_devices(devices)
    graphdef, params = nnx.split(ERNet(model_config, rngs=nnx.Rngs(0)))
    tx, train_step, _ = trainer.make_steps(graphdef, config)
    params, opt_state = jax.device_put((params, tx.init(params)), placement.state)
    samples = dataset.synthetic_samples(2 * batch_size, seed=0)
    ones = np.ones(batch_size, np.float32)
    batches = [
        jax.device_put(dataset.make_batch(samples, np.arange(i * batch_size, (i + 1) * batch_size), ones), placement.batch)
        for i in range(2)
    ]
    scale = jnp.float32(1.0)
    start = time.perf_counter()
    params, opt_state, stats = train_step(params, opt_state, batches[0], jax.random.key(0), scale)
    jax.block_until_ready(stats)
    compile_s = time.perf_counter() - start
    for i in range(2):  # warm-up
        params, opt_state, stats = train_step(params, opt_state, batches[i % 2], jax.random.key(i), scale)
    jax.block_until_ready((params, stats))
    start = time.perf_counter()
    for i in range(steps):
        params, opt_state, stats = train_step(params, opt_state, batches[i % 2], jax.random.key(i), scale)
    jax.block_until_ready((params, stats))
    elapsed = time.perf_counter() - start
    return {"samples_per_s": steps * batch_size / elapsed, "compile_s": compile_s, "devices_seen": len(jax.devices())}


def _run_child(args: argparse.Namespace, devices: int) -> dict:
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={args.devices}".strip()
    command = [sys.executable, __file__, "--child", str(devices), "--model", args.model, "--steps", str(args.steps),
               "--batch-size", str(args.batch_size), "--devices", str(args.devices)]
    done = subprocess.run(command, env={**os.environ, "XLA_FLAGS": flags}, capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"child with devices={devices} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", choices=("light", "tiny"), default="light")
    parser.add_argument("--devices", type=int, default=2, help="the data-parallel width compared with 1 (default 2)")
    parser.add_argument("--steps", type=int, default=30, help="timed steps per measurement")
    parser.add_argument("--batch-size", type=int, default=128)
    parser.add_argument("--rounds", type=int, default=2, help="alternating measurements per setting")
    parser.add_argument("--child", type=int, default=0, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        print(json.dumps(measure(args.model, args.child, args.steps, args.batch_size)))
        return

    load_before = os.getloadavg()[0]
    results: dict[int, list[dict]] = {1: [], args.devices: []}
    for _ in range(args.rounds):
        for devices in results:
            results[devices].append(_run_child(args, devices))
            print(f"devices={devices}: {results[devices][-1]['samples_per_s']:.1f} samples/s", file=sys.stderr)
    base = statistics.median(r["samples_per_s"] for r in results[1])
    print(f"\nE-RNet {args.model}, batch {args.batch_size}, {args.steps} steps per measurement, {os.cpu_count()} CPU cores split "
          f"into {args.devices} XLA devices; load average {load_before:.1f} before, {os.getloadavg()[0]:.1f} after\n")
    print("| devices | samples/s (each round) | median | vs 1 device | compile s |")
    print("|---|---|---|---|---|")
    for devices, rows in results.items():
        rates = [r["samples_per_s"] for r in rows]
        median = statistics.median(rates)
        compile_s = statistics.median(r["compile_s"] for r in rows)
        print(f"| {devices} | {' / '.join(f'{x:.1f}' for x in rates)} | {median:.1f} | {median / base:.2f}x | {compile_s:.1f} |")


if __name__ == "__main__":
    main()
