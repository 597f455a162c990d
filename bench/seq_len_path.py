"""Through which modules ``seqvpr match``'s sequence length reaches the kernel: the seqvpr modules on the call stack
when ``sequence_topk`` is entered (the call chain), and every seqvpr module a function of which received the length
on the way (an int named ``seq_len``/``length``, or a spec, settings or matcher holding it). Run from the repository
root; it makes a small synthetic route and map in ``--work``:

    .venv/bin/python bench/seq_len_path.py --work runs/seq-len-path
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

LENGTH = 7


def carries(name: str, value) -> bool:
    """Whether an argument is the length, or holds it."""
    if name in ("seq_len", "length") and value == LENGTH:
        return True
    if isinstance(value, dict) and value.get("seq_len") == LENGTH:
        return True
    spec = getattr(value, "sequence", None) or getattr(getattr(value, "settings", None), "sequence", None)
    spec = value if spec is None and type(value).__name__ == "SequenceSpec" else spec
    return getattr(spec, "length", None) == LENGTH


def trace(arguments: list[str]) -> tuple[list[str], list[str]]:
    """(the call chain's modules, every module that received the length) for ``seqvpr ARGUMENTS``."""
    chain: list[str] = []
    received: list[str] = []

    def profile(frame, event, arg):
        if event != "call" or chain:
            return
        module = frame.f_globals.get("__name__", "")
        if not module.startswith("seqvpr"):
            return
        code = frame.f_code
        names = code.co_varnames[: code.co_argcount + code.co_kwonlyargcount]
        if any(carries(n, frame.f_locals.get(n)) for n in names) and module not in received:
            received.append(module)
        if code.co_name == "sequence_topk":
            f = frame
            while f is not None:
                name = f.f_globals.get("__name__", "")
                if name.startswith("seqvpr") and name != "seqvpr.cli" and name not in chain:
                    chain.insert(0, name)
                f = f.f_back

    from seqvpr.cli import main

    sys.argv = ["seqvpr", *arguments]
    sys.setprofile(profile)
    try:
        main()
    except SystemExit:
        pass
    finally:
        sys.setprofile(None)
    return chain, received


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, required=True)
    parser.add_argument("--map", action="store_true", help="Match against a saved map of the reference.")
    args = parser.parse_args()
    import seqvpr
    from seqvpr.data.sources import save_traversal_npz
    from seqvpr.synthetic.routes import generate_route

    args.work.mkdir(parents=True, exist_ok=True)
    reference, query = generate_route(n_frames=200, dim=16, seed=1)
    save_traversal_npz(args.work / "ref.npz", reference)
    save_traversal_npz(args.work / "qry.npz", query)
    side = ["-r", str(args.work / "ref.npz")]
    if args.map:
        if not (args.work / "map" / "map.json").exists():
            seqvpr.build_map([str(args.work / "ref.npz")], args.work / "map")
        side = ["--map", str(args.work / "map")]
    chain, received = trace(["match", *side, "-q", str(args.work / "qry.npz"), "-L", str(LENGTH), "--radius", "5m",
                             "--out", str(args.work / "out"), "--json"])
    print(f"call chain, {len(chain)} modules: {' -> '.join(chain)}", file=sys.stderr)
    print(f"received it, {len(received)} modules: {', '.join(received)}", file=sys.stderr)


if __name__ == "__main__":
    main()
