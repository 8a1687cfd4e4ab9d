"""Figures of the automated-dispensing paper (Huang et al., Appl. Sci. 2023, 13(16), 9206) that the
path planning is compared with, transcribed from its tables and prose (../shared/seeds/001_*.txt).
"""

from __future__ import annotations

import numpy as np

# Table 9: the 20 dispensing positions of the dispensing-quality experiment (Figure 27), in the
# order the paper lists them: image coordinates (px), angle (deg), actual dispensing coordinates
# (machine mm, from the hand–eye calibration), dispensing area (px).
TABLE9_IMAGE_PX = np.array([
    (629.28, 713.64), (1999.52, 1128.5), (1108.04, 1598.28), (264.48, 1550.5), (2186.52, 579.12),
    (1374.84, 1903.8), (2031.04, 2197.92), (642.96, 2008.68), (948.48, 2058.84), (2243.52, 2496.6),
    (1051.08, 2421.36), (836.76, 446.88), (1942.56, 2118.13), (978.12, 1459.2), (585.96, 1146.84),
    (565.44, 937.08), (2268.6, 884.64), (563.16, 1422.72), (2154.6, 1561.9), (886.92, 1694.06),
])
TABLE9_ANGLE_DEG = np.array([
    135.6, 165.2, 36.2, 64.8, 95.6, 308.9, 225.8, 294.3, 10.8, 302.2,
    260.5, 159.7, 122.3, 231.9, 56.2, 78.3, 170.8, 264.9, 320.5, 83.7,
])
TABLE9_MACHINE_MM = np.array([
    (27.6, 31.3), (87.7, 49.5), (48.6, 70.1), (11.6, 68.0), (95.9, 25.4),
    (60.3, 83.5), (88.8, 96.4), (28.2, 88.1), (41.6, 90.3), (98.4, 109.5),
    (46.1, 106.2), (36.7, 19.6), (85.2, 92.9), (42.9, 64.1), (25.7, 50.3),
    (24.8, 41.1), (99.5, 38.8), (24.7, 62.4), (94.5, 68.5), (38.9, 74.3),
])
TABLE9_AREA_PX = np.array([
    2236, 2245, 2231, 2229, 2236, 2227, 2239, 2236, 2234, 2225,
    2226, 2227, 2236, 2234, 2238, 2229, 2237, 2231, 2228, 2233,
])
HOME_MM = (0.0, 0.0)  # the needle starts from and returns to the origin (§3.2.1, Figure 15)

# Table 3: simulated annealing settings.
ANNEALING_T0 = 1000.0
ANNEALING_COOLING = 0.98
ANNEALING_ITERATIONS = 500

# Prose of §4.3 with Figures 24–25: 20 points (another placement than Table 9's, not tabulated),
# conventional path 1670.2 mm (planned in 4.3 s), annealing 946.8 mm (2.3 s), 723.4 mm shorter.
CONVENTIONAL_20_MM = 1670.2
ANNEALED_20_MM = 946.8
# Table 4: group means of 30 runs of 20 randomly placed boards (max and min dropped): conventional,
# optimised path length (mm).
TABLE4_GROUPS_MM = np.array([(1654.9, 940.1), (1713.4, 959.8), (1707.4, 949.2)])
# Table 8: 20 dispensings per group, traditional and optimised dispensing time (s), improvement.
TABLE8_TIMES_S = np.array([
    (429.4, 297.6), (420.3, 298.0), (397.6, 295.1), (374.0, 293.6), (396.4, 298.1),
])
TABLE8_IMPROVEMENT = np.array([0.307, 0.291, 0.258, 0.215, 0.248])
# §4.5: path planning of the Table 9 points took 0.61 s.
TABLE9_PLANNING_S = 0.61
