"""Why the rescaler gathers its lookup table with cv2.remap: numpy's take, timed in the same run.

    python benchmarks/lookup_gather.py [--repeats 100]

Both gather table[round(column)] for a 480x640 float32 column image from a 4097-entry
float32 table. numpy's take needs integer indices, so it pays for a float -> int64 cast of
the whole image (2.4 MB, page-faulted afresh each frame); cv2.remap rounds as it reads and
runs on every core. Prints one JSON object of medians in milliseconds and their ratio.
"""

import argparse
import json

import cv2
import numpy as np

from companion.tools.bench import interleaved_medians_ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=100)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    table = np.linspace(0.5, 65.0, 4097, dtype=np.float32)[None, :]
    columns = rng.uniform(0, 4096, (480, 640)).astype(np.float32)

    def numpy_take():
        return table[0].take((columns + np.float32(0.5)).astype(np.intp))

    def opencv_remap():
        return cv2.remap(table, columns, np.zeros_like(columns), cv2.INTER_NEAREST)

    assert np.array_equal(numpy_take()[columns % 1 != 0.5], opencv_remap()[columns % 1 != 0.5])
    take_ms, remap_ms = interleaved_medians_ms([numpy_take, opencv_remap], args.repeats)
    print(json.dumps({"image": [480, 640], "table": 4097, "numpy_take_ms": round(take_ms, 4),
                      "cv2_remap_ms": round(remap_ms, 4),
                      "take_over_remap": round(take_ms / remap_ms, 2)}))


if __name__ == "__main__":
    main()
