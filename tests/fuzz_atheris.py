"""Coverage-guided fuzzing of one reader with atheris (libFuzzer), beside the mutation harness.

    pip install atheris
    python -m tests.fuzz_atheris hdf5 -atheris_runs=20000 -max_len=65536

The corpus starts from the same valid seed as ``tests.fuzz_harness``; any
exception other than ``AfmtoolError`` (or a crash) stops the run with the input.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import atheris

with atheris.instrument_imports():
    from afmtool.errors import AfmtoolError
    from tests.fuzz_harness import READERS, materialise, read_target, seed_input


def main() -> None:
    reader = sys.argv[1] if len(sys.argv) > 1 and sys.argv[1] in READERS else None
    if reader is None:
        raise SystemExit(f"usage: python -m tests.fuzz_atheris {{{','.join(READERS)}}} [libFuzzer flags]")
    folder = Path(tempfile.mkdtemp(prefix=f"atheris-{reader}-"))
    seed = seed_input(folder, reader)
    corpus = folder / "corpus"
    corpus.mkdir()
    source = next(p for p in seed.iterdir() if p.suffix in (".mcap", ".db3")) if seed.is_dir() else seed
    (corpus / "seed").write_bytes(source.read_bytes())
    target = read_target(reader)

    def one_input(data: bytes) -> None:
        try:
            target(materialise(seed, data, folder))
        except AfmtoolError:
            pass

    atheris.Setup([sys.argv[0], *sys.argv[2:], str(corpus)], one_input)
    atheris.Fuzz()


if __name__ == "__main__":
    main()
