# A slow (1 m/s) RTK drive over 7 s: positions of the slow drive pulled halfway to their median.
import sys; sys.path.insert(0, "/tmp/h34g"); sys.path.insert(0, "/tmp/h34g/src")
from lib import *; import numpy as np
from roadsurf.io.drive import load_drive
h, r = gps("slow")
lat = np.array([float(x["lat"]) for x in r]); lon = np.array([float(x["lon"]) for x in r])
mlat, mlon = np.median(lat), np.median(lon)
r2 = []
for x in r:
    x = dict(x); x["lat"] = f"{mlat + 0.5 * (float(x['lat']) - mlat):.9f}"; x["lon"] = f"{mlon + 0.5 * (float(x['lon']) - mlon):.9f}"; r2.append(x)
d = make_drive("slow", "chk_1mps", gps_csv=(h, r2))
dr = load_drive(d, check_images=False)
for w in dr.warnings: print("W:", w)
print("obd kept:", dr.obd is not None)
