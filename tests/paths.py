"""Where the tests find data: the sample scene and the reference checkpoint (MIT, with its
licence) ship with the repository."""

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE_DIR = REPO / "examples" / "ue_sample"
REFERENCE_CHECKPOINT = REPO / "tests" / "data" / "reference" / "shadowcorr_best.pth"
