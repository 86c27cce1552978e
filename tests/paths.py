"""Where the tests find data: the sample scene ships with the repository; the reference
checkpoint lives in the shared folder beside the checkout (tests needing it skip without it)."""

from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE_DIR = REPO / "examples" / "ue_sample"
REFERENCE_CHECKPOINT = REPO.parent / "shared" / "reference" / "shadowcorr_best.pth"
