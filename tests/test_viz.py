"""Flow colours, warping and panels on tiny cases with hand-known answers."""

import cv2
import numpy as np

from ufm_jax.runtime import viz
from ufm_jax.data import io


def test_colorwheel_is_middlebury():
  wheel = viz.make_colorwheel()
  assert wheel.shape == (55, 3)
  np.testing.assert_array_equal(wheel[0], [255, 0, 0])     # red
  np.testing.assert_array_equal(wheel[15], [255, 255, 0])  # yellow
  np.testing.assert_array_equal(wheel[21], [0, 255, 0])    # green
  np.testing.assert_array_equal(wheel[25], [0, 255, 255])  # cyan
  np.testing.assert_array_equal(wheel[36], [0, 0, 255])    # blue
  np.testing.assert_array_equal(wheel[49], [255, 0, 255])  # magenta
  np.testing.assert_array_equal(wheel[1], [255, 17, 0])    # floor(255 / 15) = 17


def test_flow_colours_known_hues():
  flow = np.zeros((1, 5, 2), np.float32)
  flow[0, 1] = (4, 0)    # +u at max magnitude -> red
  flow[0, 2] = (2, 0)    # +u at half magnitude -> half-saturated red
  flow[0, 3] = (-4, 0)   # -u -> wheel entry 27 = (0, 255 - floor(255 * 2 / 11), 255)
  flow[0, 4] = (0, -4)   # -v (up) -> wheel position 40.5: between entries 40 and 41 (blue->magenta)
  rgb = viz.flow_to_color(flow)
  np.testing.assert_array_equal(rgb[0, 0], [255, 255, 255])  # zero flow is white
  np.testing.assert_array_equal(rgb[0, 1], [255, 0, 0])
  np.testing.assert_array_equal(rgb[0, 2], [255, 127, 127])
  np.testing.assert_array_equal(rgb[0, 3], [0, 209, 255])
  r40, r41 = np.floor(255 * 4 / 13), np.floor(255 * 5 / 13)
  assert abs(int(rgb[0, 4, 0]) - (r40 + r41) / 2) <= 1 and rgb[0, 4, 1] == 0 and rgb[0, 4, 2] == 255


def test_flow_colours_saturate_above_max():
  flow = np.array([[[8.0, 0.0]]], np.float32)
  np.testing.assert_array_equal(viz.flow_to_color(flow, max_flow=4.0)[0, 0], [191, 0, 0])  # 0.75*255


def test_warp_by_integer_flow_is_a_roll():
  rng = np.random.default_rng(0)
  target = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
  flow = np.zeros((12, 16, 2), np.float32)
  flow[..., 0], flow[..., 1] = 3, -2   # source (x, y) looks at target (x + 3, y - 2)
  warped = viz.warp_by_flow(target, flow)
  rolled = np.roll(target, (2, -3), axis=(0, 1))
  np.testing.assert_array_equal(warped[2:, :-3], rolled[2:, :-3])
  assert (warped[:2] == 0).all() and (warped[:, -3:] == 0).all()  # outside the target


def test_grey_out_and_panel(tmp_path):
  img = np.zeros((6, 8, 3), np.uint8)
  img[..., 0] = 200
  covis = np.ones((6, 8), np.float32)
  covis[:, :4] = 0.2
  out = viz.grey_out(img, covis)
  np.testing.assert_array_equal(out[:, 4:], img[:, 4:])
  luma = 0.299 * 200
  np.testing.assert_array_equal(out[:, :4], np.round(128 + (luma - 128) / 4))
  p = viz.panel(img, img[:3, :5], np.zeros((6, 8, 2), np.float32), covis)
  # 6 px images: the row enlarged 22x (ceil(128 / 6)), each pixel a 22 x 22 block
  assert p.shape == (6 * 22, 4 * 8 * 22, 3) and p.dtype == np.uint8
  np.testing.assert_array_equal(p[::22, :8 * 22:22], img)
  np.testing.assert_array_equal(p, np.repeat(np.repeat(p[::22, ::22], 22, 0), 22, 1))
  assert viz.panel(np.zeros((128, 130, 3), np.uint8), img, np.zeros((128, 130, 2), np.float32)
                   ).shape == (128, 4 * 130, 3)   # large enough: as it is
  path = tmp_path / "panel.png"
  io.write_image(path, p)
  np.testing.assert_array_equal(io.read_image(path), p)
  grey = viz.covisibility_to_image(covis)
  io.write_image(tmp_path / "c.png", grey)
  np.testing.assert_array_equal(cv2.imread(str(tmp_path / "c.png"), cv2.IMREAD_UNCHANGED), grey)
