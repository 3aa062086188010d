"""Step 1 (1_gcp_finder): find the images that see each GCP; GUI to mark them; write gcp_list.txt."""

from matchplant.gcp_finder import GcpFinderConfig, run
from matchplant.steps import StepSpec

SPEC = StepSpec(
    name="gcp_finder",
    config=GcpFinderConfig,
    run=run,
    gui="matchplant.gcp_finder.gui:launch",
    flags={
        "--images": ("images", "folder of the images"),
        "--survey": ("survey", "GCP survey table id,x,y,z"),
        "--crs": ("survey_crs", "CRS of the survey, e.g. EPSG:32614"),
    },
)
