"""
The CNN of the node's pipeline, ROS-free: loaded up front, its precision, its warnings.

Shared by the nodes and gcp-stereo-bag run. torch comes with the CNN (stereo.cnn), an
optional dependency here: it is imported only where GCPs are used, so that a pipeline
without them runs without it.
"""
import numpy as np

from ..stereo.cnn.weights import int8_entry


def load_cnn(pipeline):
    """Return `pipeline` with its CNN loaded if it uses GCPs: weights that cannot work raise."""
    if pipeline.config.use_gcp:
        pipeline.net  # a missing, broken or uncalibrated weights file raises here
    return pipeline


def cnn_precision(config):
    """Say how a StereoConfig runs the CNN: 'int8', 'bf16', 'fp32' or 'not used'."""
    if not config.use_gcp:
        return 'not used'
    from ..stereo.cnn.network import resolve_precision  # optional: torch
    return resolve_precision(config.precision, config.device,
                             int8_entry(config.weights) is not None)


def config_warnings(pipeline):
    """Return what is wrong with a valid pipeline's config as used on a stream, as sentences."""
    config = pipeline.config
    if config.use_gcp:
        from ..stereo.cnn.network import calibrated  # optional: torch
        top = float(calibrated(pipeline.net, np.ones(1, np.float32),
                               config.matched_radius)[0])
        if config.theta >= top:
            return [f'theta {config.theta:g} selects no GCP: the CNN confidence is at most '
                    f'{top:.3g} with these weights, so every pixel gets c_hi at every '
                    'disparity and the disparity is 0 everywhere; lower theta or set use_gcp '
                    'false']
    return []
