#!/usr/bin/env python3
"""Ship a head trained on a BASE as the head alone: the tensors it shares with the BASE file are
left out and filled in from it at load time (its SHA-256 checked), so that a carry head costs
0.6 MB beside the 9 MB BASE instead of a second copy of it.

    python scripts/save_on_base.py ../runs/carry5/weights.safetensors models/carry.safetensors --base models/cnn.safetensors
"""

from __future__ import annotations

import argparse

from mosaic_cli.model.checkpoint import load_weights, save_on_base


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("weights", help="the trained run's weights.safetensors (whole)")
    ap.add_argument("out", help="where the head goes, beside its BASE")
    ap.add_argument("--base", required=True, help="the BASE file the head was trained on")
    args = ap.parse_args()
    net, meta = load_weights(args.weights)
    save_on_base(args.out, net, args.base, meta["variant"], meta["extra"], tuple(meta["work_size"]), meta["int8"])
    again, _ = load_weights(args.out)
    assert all(v.equal(again.state_dict()[k]) for k, v in net.state_dict().items()), "the saved head does not load back whole"
    print(f"{args.out}: {meta['variant']} on {args.base}")


if __name__ == "__main__":
    main()
