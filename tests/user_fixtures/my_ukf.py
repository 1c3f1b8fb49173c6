"""A quaternion UKF as a student builds it with FilterPy: the state is the quaternion itself."""
import numpy as np
from filterpy.kalman import JulierSigmaPoints, UnscentedKalmanFilter

from fusion.estimators.adapters.filterpy import from_filterpy

G = 9.80665


def qmul(a, b):
    w0, x0, y0, z0 = a
    w1, x1, y1, z1 = b
    return np.array([w0*w1 - x0*x1 - y0*y1 - z0*z1, w0*x1 + x0*w1 + y0*z1 - z0*y1,
                     w0*y1 - x0*z1 + y0*w1 + z0*x1, w0*z1 + x0*y1 - y0*x1 + z0*w1])


def fx(x, dt, gyro):
    """Integrate the gyro over dt: q * exp(gyro dt / 2)."""
    angle = np.linalg.norm(gyro) * dt
    axis = gyro / np.linalg.norm(gyro) if angle > 0 else np.zeros(3)
    q = qmul(x, np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis]))
    return q / np.linalg.norm(q)


def hx(x):
    """The accelerometer at rest: gravity in the body frame, R^T [0, 0, g], m/s^2."""
    w, x_, y, z = x / np.linalg.norm(x)
    return G * np.array([2 * (x_ * z - w * y), 2 * (y * z + w * x_), w * w - x_ * x_ - y * y + z * z])


def mean_quaternion(sigmas, weights):
    signs = np.where(sigmas @ sigmas[0] < 0, -1.0, 1.0)
    q = weights @ (sigmas * signs[:, None])
    return q / np.linalg.norm(q)


def residual(a, b):
    return a - b if a @ b >= 0 else -a - b


def make_ukf(q0, dt, gyro_noise=0.02, acc_noise=2.0):
    ukf = UnscentedKalmanFilter(dim_x=4, dim_z=3, dt=dt, fx=fx, hx=hx,
                                points=JulierSigmaPoints(4, kappa=0.0),
                                x_mean_fn=mean_quaternion, residual_x=residual)
    ukf.x = np.array(q0, dtype=float)
    ukf.P = np.eye(4) * 1e-4
    ukf.Q = np.eye(4) * (0.5 * gyro_noise) ** 2 * dt
    ukf.R = np.eye(3) * acc_noise ** 2
    return ukf


def normalised(x):
    return x / np.linalg.norm(x)


MyUKF = from_filterpy(make_ukf, quaternion=normalised)
