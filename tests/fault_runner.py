"""A helper process for tests/test_faults.py: runs ``lfrig`` commands in forked children.

Started once per test module with ``NUMBA_THREADING_LAYER=workqueue`` (numba's fork-safe layer; the
OpenMP one refuses to run in a forked child), it reads one JSON request per line on stdin and
answers one JSON line on stdout:

- ``{"run": ARGS, "fault": "kill:N" | "enospc:N" | null, "log": FILE | null}``: fork, set the fault
  hook's variables in the child (``recon.lf.imageio.FAULT_ENV``), run ``rig.main.main(ARGS)`` there;
  answer ``{"status": exit status or -signal, "out": ..., "err": ...}``. The modules are imported and
  the numba kernels compiled once, in this process, so a run costs what the command costs.
- ``{"warm": ARGS}``: run the command here, unforked, so its kernels are compiled before the forks.
- ``{"stand_in": "calibrate"}``: replace the calibration solves by fixed results (see
  :func:`stand_in_calibration`); the calibrate commands' writes stay real.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import tempfile
import time
import traceback

TIMEOUT_S = 120.0


def stand_in_calibration() -> None:
    """The solves of ``calibrate intrinsics`` / ``calibrate stage`` replaced by their results: a
    pinhole model and a fixed stage geometry. What the fault sweep exercises is the writing."""
    import cv2
    import mrcal
    import numpy as np

    import calib.intrinsics
    import calib.stage

    class Result:
        model = mrcal.cameramodel(intrinsics=("LENSMODEL_PINHOLE", np.array([400.0, 400.0, 79.5, 60.5])),
                                  imagersize=np.array([160, 122]))

        def report(self) -> str:
            return "RMS reprojection error 0.1 px (stand-in for the solve)"

    def residual_picture(result, path):
        if not cv2.imwrite(str(path), np.full((122, 160, 3), 200, np.uint8)):
            raise OSError(f"could not write {path}")

    calib.intrinsics.calibrate_intrinsics_from_images = lambda *a, **k: Result()
    calib.intrinsics.write_residual_picture = residual_picture
    calib.stage.calibrate_stage_from_capture = lambda *a, **k: (stage(), None)


def stage(pitch_mm: float = 0.5):
    import numpy as np

    from calib.stage import StageCalibration

    return StageCalibration(grid=(3, 3), pitch_mm=pitch_mm, step_u_mm=np.array([0.0, pitch_mm * 1.002, 0.0]),
                            step_v_mm=np.array([pitch_mm, 0.001, 0.0]), r_cam_board=np.zeros(3),
                            t_cam_board_mm=np.array([0.0, 0.0, 950.0]), rms_px=0.1, max_px=0.3, n_views=9,
                            n_corners=0, n_outliers=0)


def run_forked(args: list[str], fault: str | None, log: str | None) -> dict:
    import recon.lf.imageio as imageio
    from rig.main import main

    with tempfile.TemporaryDirectory() as scratch:
        out_path, err_path = os.path.join(scratch, "out"), os.path.join(scratch, "err")
        pid = os.fork()
        if pid == 0:  # the child
            code = 97
            try:
                out_fd = os.open(out_path, os.O_WRONLY | os.O_CREAT)
                err_fd = os.open(err_path, os.O_WRONLY | os.O_CREAT)
                os.dup2(out_fd, 1)
                os.dup2(err_fd, 2)
                sys.stdout = open(1, "w", closefd=False)
                sys.stderr = open(2, "w", closefd=False)
                for key in (imageio.FAULT_ENV, imageio.FAULT_LOG_ENV):
                    os.environ.pop(key, None)
                if fault:
                    os.environ[imageio.FAULT_ENV] = fault
                if log:
                    os.environ[imageio.FAULT_LOG_ENV] = log
                imageio._writes = 0
                code = main(list(args))
            except BaseException:  # noqa: BLE001 - reported through the status and stderr
                traceback.print_exc()
                code = 98
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(code if isinstance(code, int) else 96)
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() > deadline:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                return {"status": "timeout", "out": "", "err": ""}
            time.sleep(0.005)
        with open(out_path, errors="replace") as f:
            out = f.read()
        with open(err_path, errors="replace") as f:
            err = f.read()
    code = -os.WTERMSIG(status) if os.WIFSIGNALED(status) else os.WEXITSTATUS(status)
    return {"status": code, "out": out, "err": err}


def serve() -> None:
    import rig.main  # noqa: F401 - import everything once, before the first fork

    reply = sys.stdout
    sys.stdout = sys.stderr  # what the commands print must not mix with the answers
    for line in sys.stdin:
        request = json.loads(line)
        try:
            if "run" in request:
                answer = run_forked(request["run"], request.get("fault"), request.get("log"))
            elif "warm" in request:
                from rig.main import main

                answer = {"status": main(list(request["warm"]))}
            elif request.get("stand_in") == "calibrate":
                stand_in_calibration()
                answer = {"status": 0}
            else:
                answer = {"status": "unknown request"}
        except BaseException as error:  # noqa: BLE001
            answer = {"status": "error", "err": f"{type(error).__name__}: {error}\n{traceback.format_exc()}"}
        reply.write(json.dumps(answer) + "\n")
        reply.flush()


if __name__ == "__main__":
    serve()
