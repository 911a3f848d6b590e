"""Ground-truth benchmark scenes rendered with Mitsuba 3 (see ``docs/synth.md``).

The heavy imports (mitsuba, scikit-image, OpenCV) happen only when a scene is rendered.
"""

from rtsplat.synth.dataset import SynthConfig, SynthSummary, render_dataset
from rtsplat.synth.scenes import SCENES, SceneSpec, build_scene

__all__ = ["SCENES", "SceneSpec", "SynthConfig", "SynthSummary", "build_scene", "render_dataset"]
