"""The calibrated confidence's logistic model (recon/entropy/calibration.py), written by
``bench/confidence_fit.py fit DATA --write recon/entropy/confidence_fit.py``."""

FIT = {
    "features": [
        "log_width",
        "log_change",
        "log_neighbour",
        "log_initial",
        "occluding",
        "occluded",
        "texture",
        "hole",
        "noise_limited",
        "log_cost",
        "window_size",
        "log_slope",
        "heuristic"
    ],
    "bias": -3.181654341146866,
    "coefficients": [
        -0.11147760811974185,
        -0.3197854494210102,
        -0.134486324520359,
        -0.43970970246905167,
        -0.20169780232763457,
        -0.22526882906871307,
        0.511547401111773,
        0.13969467587646547,
        0.1634016379265844,
        -0.7985486752993746,
        0.39033274918883315,
        -0.3836414823711703,
        2.4863661443958263
    ],
    "target": "P(|d - truth| <= 0.07 px/view)",
    "scenes": [
        "backgammon",
        "glossy-v1",
        "occlusion-v1",
        "slanted-v1",
        "slanted-v2",
        "suite-bars-s0-192",
        "suite-boxes-s0-192",
        "suite-cotton-s0-192",
        "suite-dots-s0-192",
        "suite-noisy-s0-192",
        "suite-pyramids-s0-192",
        "suite-slants-s0-192",
        "suite-stripes-s0-192",
        "suite-thin-s0-192",
        "weaktexture-v1"
    ],
    "pixels_per_scene": 20000,
    "ridge": 0.001
}
