"""The live view: a domain's arms, markers, cameras and joint curves in Rerun's web viewer, served on loopback.

    uniros view --domain tcp://127.0.0.1:7400      # live
    uniros view --bag run.mcap                     # a bag, with the viewer's time slider

``ViewerServer`` runs the Rerun viewer's own server (the ``rerun`` program of the rerun-sdk wheel, which carries the
web app: nothing is fetched from the internet) bound to 127.0.0.1; ``SceneLogger`` turns bus messages into Rerun
entities (the arm's geoms posed by MuJoCo forward kinematics of its MJCF, markers, images, plots);
``view_domain`` and ``view_bag`` feed it; ``screenshot`` drives a headless Chromium over the DevTools protocol.
"""

from __future__ import annotations

from uniros_async.errors import ViewError

__all__ = ["ViewError"]
