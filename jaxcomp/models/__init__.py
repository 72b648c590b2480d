"""Built-in robot models, MJCF files authored for jaxcomp from published figures."""

from pathlib import Path

MODEL_DIR = Path(__file__).parent

BUILTIN = {
    "gen3_lite": MODEL_DIR / "gen3_lite.xml",
    "dingo_o": MODEL_DIR / "dingo_o.xml",
    "mobile_gen3_lite": MODEL_DIR / "mobile_gen3_lite.xml",
    "gen3": MODEL_DIR / "gen3.xml",
    "wx250s": MODEL_DIR / "wx250s.xml",
}
