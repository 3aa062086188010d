"""Step 0 (0_gps_embeder): write GNSS positions into image EXIF by matching timestamps."""

from matchplant.gps_embeder import GpsEmbederConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="gps_embeder",
    config=GpsEmbederConfig,
    run=run,
    flags={
        "--images": ("images", "folder of the images"),
        "--log": ("gnss_log", "GNSS event log"),
        "--crs": ("log_crs", "CRS of the log, e.g. EPSG:32614"),
    },
)
