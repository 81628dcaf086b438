"""Real-fleet dimension statistics per fine vehicle kind, and the sampler that draws from them.

Each kind lists best-selling or typical models of its segment with their manufacturer-published
exterior dimensions (length, width without mirrors, height, wheelbase; mm; the generation's
launch years). The car and van figures are the makers' brochure / press-kit values for a common
body variant, written down from memory (accurate to a few centimetres); for trucks, buses and
trailers the list holds typical chassis + body combinations and the legal maxima bound them (EU: width
2.55 m, 2.60 m refrigerated, length of a semi-trailer's box 13.6 m; US: width 102 in = 2.59 m,
53 ft = 16.15 m trailers, height 13 ft 6 in = 4.11 m). docs/vehicles.md states the sources.

Sampling (`sample_dimensions`): a multivariate normal with the mean and covariance of the listed
models (so length, width, height and wheelbase stay correlated as in the real fleet), the
covariance floored at a minimum spread per dimension, truncated by rejection to
``[min - margin, max + margin]`` of the listed models (`dimension_bounds`). Kinds with distinct
sub-populations (semi-trailers: 13.6 m EU boxes and 48/53 ft US vans; tractors: cab-over and
long-nose conventionals) list each population under its own style key.
"""

from __future__ import annotations

import numpy as np

from seqshape.errors import ConfigError

# kind -> style -> [(model, years, length, width, height, wheelbase)] in mm
FLEET_MODELS: dict[str, dict[str, list[tuple[str, str, int, int, int, int]]]] = {
    "city_car": {"": [
        ("Fiat 500", "2007", 3571, 1627, 1488, 2300),
        ("Volkswagen up!", "2011", 3600, 1641, 1489, 2407),
        ("Toyota Aygo", "2014", 3455, 1615, 1460, 2340),
        ("Citroen C1", "2014", 3466, 1615, 1460, 2340),
        ("Hyundai i10", "2019", 3670, 1680, 1480, 2425),
        ("Kia Picanto", "2017", 3595, 1595, 1485, 2400),
        ("Renault Twingo", "2014", 3595, 1646, 1554, 2492),
        ("Fiat Panda", "2012", 3653, 1643, 1551, 2300),
        ("Chevrolet Spark", "2016", 3635, 1595, 1483, 2385),
    ]},
    "hatchback": {"": [
        ("Volkswagen Polo", "2017", 4053, 1751, 1461, 2548),
        ("Renault Clio", "2019", 4050, 1798, 1440, 2583),
        ("Peugeot 208", "2019", 4055, 1745, 1430, 2540),
        ("Ford Fiesta", "2017", 4040, 1735, 1476, 2493),
        ("Toyota Yaris", "2020", 3940, 1745, 1500, 2560),
        ("Opel Corsa", "2019", 4060, 1765, 1435, 2538),
        ("Volkswagen Golf", "2019", 4284, 1789, 1456, 2636),
        ("Ford Focus", "2018", 4378, 1825, 1454, 2700),
        ("Toyota Corolla hatchback", "2018", 4370, 1790, 1435, 2640),
        ("Hyundai i30", "2017", 4340, 1795, 1455, 2650),
        ("Honda Civic hatchback", "2021", 4550, 1800, 1415, 2735),
    ]},
    "sedan": {"": [
        ("Toyota Camry", "2017", 4880, 1840, 1445, 2825),
        ("Honda Accord", "2018", 4882, 1862, 1450, 2830),
        ("Toyota Corolla sedan", "2019", 4630, 1780, 1435, 2700),
        ("Honda Civic sedan", "2022", 4674, 1802, 1415, 2735),
        ("Hyundai Elantra", "2021", 4675, 1825, 1430, 2720),
        ("Nissan Altima", "2019", 4900, 1850, 1440, 2825),
        ("Tesla Model 3", "2017", 4694, 1849, 1443, 2875),
        ("BMW 3 Series", "2019", 4709, 1827, 1442, 2851),
        ("Mercedes-Benz C-Class", "2021", 4751, 1820, 1438, 2865),
        ("Volkswagen Passat", "2014", 4767, 1832, 1456, 2791),
        ("Audi A4", "2015", 4762, 1842, 1428, 2820),
        ("BMW 5 Series", "2017", 4936, 1868, 1479, 2975),
        ("Mercedes-Benz E-Class", "2016", 4923, 1852, 1468, 2939),
    ]},
    "estate": {"": [
        ("Skoda Octavia Combi", "2020", 4689, 1829, 1468, 2686),
        ("Volkswagen Golf Variant", "2020", 4633, 1789, 1498, 2686),
        ("Volkswagen Passat Variant", "2014", 4767, 1832, 1477, 2791),
        ("Skoda Superb Combi", "2015", 4856, 1864, 1477, 2841),
        ("BMW 3 Series Touring", "2019", 4709, 1827, 1445, 2851),
        ("Mercedes-Benz E-Class Estate", "2016", 4933, 1852, 1475, 2939),
        ("Volvo V60", "2018", 4761, 1850, 1432, 2872),
        ("Audi A4 Avant", "2015", 4762, 1842, 1434, 2820),
        ("Ford Focus Turnier", "2018", 4668, 1825, 1481, 2700),
        ("Toyota Corolla Touring Sports", "2019", 4650, 1790, 1460, 2700),
    ]},
    "coupe": {"": [
        ("Ford Mustang", "2015", 4784, 1916, 1381, 2720),
        ("Chevrolet Camaro", "2016", 4784, 1897, 1348, 2811),
        ("BMW 4 Series Coupe", "2020", 4768, 1852, 1383, 2851),
        ("Audi A5 Coupe", "2016", 4673, 1846, 1371, 2764),
        ("Mercedes-Benz C-Class Coupe", "2015", 4686, 1810, 1405, 2840),
        ("Porsche 911", "2019", 4519, 1852, 1300, 2450),
        ("Toyota GR86", "2021", 4265, 1775, 1310, 2575),
        ("Audi TT", "2014", 4191, 1832, 1353, 2505),
        ("Mazda MX-5", "2015", 3915, 1735, 1225, 2310),
    ]},
    "mpv": {"": [
        ("Toyota Sienna", "2021", 5175, 1995, 1775, 3060),
        ("Honda Odyssey", "2018", 5161, 1994, 1735, 3000),
        ("Chrysler Pacifica", "2017", 5176, 2022, 1777, 3089),
        ("Kia Carnival", "2021", 5155, 1995, 1775, 3090),
        ("Volkswagen Touran", "2015", 4527, 1829, 1659, 2786),
        ("Renault Scenic", "2016", 4406, 1866, 1653, 2734),
        ("Citroen C4 SpaceTourer", "2018", 4438, 1826, 1610, 2785),
        ("Ford Galaxy", "2015", 4848, 1916, 1747, 2849),
        ("Volkswagen Sharan", "2010", 4854, 1904, 1720, 2920),
        ("Mercedes-Benz B-Class", "2019", 4419, 1796, 1562, 2729),
    ]},
    "crossover": {"": [
        ("Toyota RAV4", "2019", 4600, 1855, 1685, 2690),
        ("Honda CR-V", "2017", 4586, 1855, 1679, 2660),
        ("Nissan Qashqai", "2021", 4425, 1838, 1625, 2666),
        ("Volkswagen Tiguan", "2016", 4486, 1839, 1673, 2681),
        ("Hyundai Tucson", "2021", 4500, 1865, 1650, 2680),
        ("Kia Sportage", "2022", 4515, 1865, 1645, 2680),
        ("Peugeot 3008", "2016", 4447, 1841, 1624, 2675),
        ("Volkswagen T-Roc", "2017", 4234, 1819, 1573, 2595),
        ("Renault Captur", "2019", 4227, 1797, 1576, 2639),
        ("Toyota C-HR", "2016", 4360, 1795, 1555, 2640),
        ("Mazda CX-5", "2017", 4550, 1840, 1680, 2700),
        ("Tesla Model Y", "2020", 4751, 1921, 1624, 2890),
        ("Ford Kuga", "2019", 4614, 1883, 1666, 2710),
        ("Hyundai Kona", "2017", 4165, 1800, 1550, 2600),
    ]},
    "suv": {"": [
        ("Toyota Highlander", "2020", 4950, 1930, 1730, 2850),
        ("Ford Explorer", "2020", 5050, 2004, 1775, 3025),
        ("Chevrolet Tahoe", "2021", 5352, 2058, 1927, 3071),
        ("Jeep Grand Cherokee", "2022", 4914, 1968, 1792, 2964),
        ("BMW X5", "2018", 4922, 2004, 1745, 2975),
        ("Mercedes-Benz GLE", "2019", 4924, 2018, 1772, 2995),
        ("Volkswagen Touareg", "2018", 4878, 1984, 1717, 2904),
        ("Volvo XC90", "2015", 4950, 1958, 1775, 2984),
        ("Land Rover Defender 110", "2020", 4758, 1996, 1967, 3022),
        ("Toyota Land Cruiser 300", "2021", 4985, 1980, 1925, 2850),
        ("Kia Sorento", "2020", 4810, 1900, 1700, 2815),
        ("Hyundai Santa Fe", "2018", 4770, 1890, 1680, 2765),
        ("Toyota 4Runner", "2010", 4830, 1925, 1780, 2790),
    ]},
    "pickup": {"": [
        ("Ford F-150 SuperCrew 5.5 ft", "2021", 5885, 2029, 1960, 3683),
        ("Chevrolet Silverado 1500 Crew 5.8 ft", "2019", 5885, 2063, 1917, 3744),
        ("Ram 1500 Crew 5.7 ft", "2019", 5816, 2085, 1971, 3569),
        ("Toyota Tundra CrewMax", "2022", 5931, 2037, 1981, 3701),
        ("Toyota Tacoma Double Cab", "2016", 5392, 1890, 1793, 3235),
        ("Toyota Hilux Double Cab", "2016", 5325, 1855, 1815, 3085),
        ("Ford Ranger SuperCrew", "2019", 5354, 1862, 1793, 3220),
        ("Nissan Navara Double Cab", "2015", 5255, 1850, 1840, 3150),
        ("Mitsubishi L200 Double Cab", "2015", 5305, 1815, 1795, 3000),
        ("Chevrolet Colorado Crew Cab", "2015", 5403, 1886, 1787, 3258),
    ]},
    "panel_van": {"": [
        ("Ford Transit Custom L1H1", "2012", 4972, 1986, 1921, 2933),
        ("Volkswagen Transporter T6 L1H1", "2015", 4904, 1904, 1990, 3000),
        ("Mercedes-Benz Vito long", "2014", 5140, 1928, 1910, 3200),
        ("Renault Trafic L1H1", "2014", 4999, 1956, 1971, 3098),
        ("Citroen Jumpy / Peugeot Expert M", "2016", 4956, 1920, 1905, 3275),
        ("Ford Transit Connect LWB", "2013", 4825, 1835, 1827, 3062),
        ("Citroen Berlingo XL", "2018", 4753, 1848, 1880, 2975),
        ("Volkswagen Caddy Maxi", "2020", 4853, 1855, 1800, 2970),
        ("Renault Kangoo", "2021", 4486, 1860, 1838, 2716),
    ]},
    "high_roof_van": {"": [
        ("Mercedes-Benz Sprinter L2H2", "2018", 5932, 2020, 2680, 3665),
        ("Mercedes-Benz Sprinter L3H2", "2018", 6967, 2020, 2720, 4325),
        ("Ford Transit L2H2", "2014", 5531, 2059, 2550, 3300),
        ("Ford Transit L3H3", "2014", 5981, 2059, 2786, 3750),
        ("Fiat Ducato L2H2", "2014", 5413, 2050, 2524, 3450),
        ("Fiat Ducato L3H2", "2014", 5998, 2050, 2524, 4035),
        ("Renault Master L2H2", "2010", 5548, 2070, 2488, 3682),
        ("Volkswagen Crafter L3H3", "2017", 5986, 2040, 2790, 3640),
        ("Ram ProMaster 2500 High Roof 159 in", "2014", 6062, 2050, 2537, 4039),
        ("Iveco Daily 35S L3H2", "2014", 5998, 1996, 2630, 3520),
    ]},
    "box_truck": {"": [
        ("Isuzu NPR + 14 ft box", "2016", 6450, 2290, 3150, 3815),
        ("Isuzu NPR-HD + 16 ft box", "2016", 7150, 2440, 3300, 4300),
        ("Ford E-350 cutaway + 14 ft box", "2015", 6950, 2290, 3200, 4050),
        ("Mercedes-Benz Atego 1224 + box", "2013", 8500, 2550, 3600, 4820),
        ("MAN TGL 12.220 + box", "2014", 8300, 2550, 3500, 4500),
        ("DAF LF 180 + box", "2014", 8600, 2550, 3650, 4900),
        ("Volvo FL 16 t + box", "2014", 9500, 2550, 3800, 5300),
        ("Hino 268 + 24 ft box", "2015", 10200, 2590, 3900, 5890),
        ("Freightliner M2 106 + 26 ft box", "2015", 10900, 2590, 4000, 6400),
    ]},
    "tractor": {
        "cabover": [
            ("Mercedes-Benz Actros 1845 LS", "2019", 6000, 2500, 3850, 3700),
            ("Scania R 450 A4x2", "2016", 5900, 2550, 3700, 3700),
            ("Volvo FH 4x2T", "2013", 5950, 2500, 3800, 3700),
            ("DAF XF 480 FT", "2017", 5900, 2550, 3900, 3800),
            ("MAN TGX 18.470 4x2", "2020", 5950, 2500, 3800, 3600),
            ("Iveco S-Way AS440", "2019", 5950, 2550, 3750, 3800),
        ],
        "conventional": [
            ("Freightliner Cascadia 126 sleeper", "2018", 8400, 2590, 4100, 5800),
            ("Volvo VNL 860", "2018", 8300, 2590, 4100, 5900),
            ("Kenworth T680 76 in sleeper", "2014", 8200, 2590, 4050, 5700),
            ("Peterbilt 579 day cab", "2013", 6700, 2590, 3500, 4600),
            ("International LT day cab", "2017", 6800, 2590, 3400, 4700),
            ("Freightliner Cascadia day cab", "2018", 6900, 2590, 3500, 4750),
        ]},
    "flatbed": {"": [
        ("Ford F-550 + 12 ft flatbed", "2017", 6900, 2440, 2450, 4300),
        ("Isuzu NRR + 20 ft flatbed", "2016", 8300, 2440, 2700, 4700),
        ("Mercedes-Benz Atego 818 dropside", "2013", 7400, 2500, 3100, 4160),
        ("Hino 338 + 24 ft flatbed", "2015", 10500, 2500, 2950, 6300),
        ("MAN TGL 8.190 dropside", "2014", 7000, 2450, 3000, 3900),
        ("Iveco Daily 70C dropside", "2014", 7100, 2300, 2800, 4350),
    ]},
    "city_bus": {"": [
        ("Mercedes-Benz Citaro 12 m", "2011", 12135, 2550, 3120, 5845),
        ("MAN Lion's City 12", "2018", 12185, 2550, 3100, 6000),
        ("Solaris Urbino 12", "2014", 12000, 2550, 3050, 5900),
        ("Volvo 7900 12 m", "2011", 12000, 2550, 3200, 5900),
        ("Gillig Low Floor 40 ft", "2010", 12190, 2590, 3200, 7000),
        ("New Flyer Xcelsior XD40", "2008", 12500, 2590, 3300, 7000),
        ("BYD K9 40 ft", "2013", 12000, 2550, 3400, 6100),
        ("Mercedes-Benz Citaro K", "2011", 10630, 2550, 3120, 4825),
    ]},
    "coach": {"": [
        ("Setra S 515 HD", "2012", 12200, 2550, 3700, 6080),
        ("Mercedes-Benz Tourismo", "2017", 12140, 2550, 3680, 6000),
        ("MCI J4500", "2001", 13800, 2600, 3500, 7500),
        ("Prevost H3-45", "1995", 13700, 2600, 3700, 7900),
        ("Van Hool CX45", "2015", 13700, 2600, 3500, 7500),
        ("Volvo 9700 13 m", "2012", 13100, 2550, 3700, 6950),
        ("Irizar i6", "2010", 12200, 2550, 3600, 6150),
        ("Neoplan Tourliner", "2016", 13000, 2550, 3800, 6870),
    ]},
    "semi_trailer": {
        "eu": [
            ("Schmitz Cargobull S.KO box", "2015", 13950, 2550, 4000, 7700),
            ("Krone Profi Liner curtainsider", "2014", 13860, 2550, 4000, 7750),
            ("Koegel Cargo curtainsider", "2015", 13900, 2550, 4000, 7700),
            ("Schmitz Cargobull S.CS curtainsider", "2015", 13950, 2550, 4000, 7750),
        ],
        "us": [
            ("Wabash DuraPlate 53 ft", "2015", 16150, 2590, 4110, 12300),
            ("Great Dane Champion 53 ft", "2015", 16150, 2590, 4110, 12200),
            ("Utility 3000R reefer 53 ft", "2015", 16150, 2600, 4110, 12300),
            ("Great Dane 48 ft dry van", "2015", 14630, 2590, 4110, 10700),
        ],
        "us_pup": [
            ("Wabash 28 ft pup", "2015", 8530, 2590, 4110, 6200),
            ("Great Dane 28 ft pup", "2015", 8530, 2590, 4110, 6100),
            ("Stoughton 28 ft pup", "2015", 8530, 2590, 4060, 6250),
        ]},
    "car_trailer": {"": [
        ("Brenderup 1205 S utility", "2015", 3000, 1570, 900, 2150),
        ("Humbaur Steely 2512 box", "2015", 3900, 1750, 950, 2800),
        ("Boeckmann TPV EU3", "2015", 3550, 1650, 1000, 2500),
        ("Big Tex 30SA 12 ft utility", "2015", 5100, 2080, 1000, 3700),
        ("Brian James A4 car transporter", "2015", 5600, 2250, 950, 3950),
        ("Humbaur car transporter FTK", "2015", 5800, 2200, 1000, 4000),
    ]},
}

# minimum standard deviation (m) per dimension (length, width, height, wheelbase)
_MIN_SD = np.array([0.06, 0.02, 0.02, 0.05])
_MARGIN = np.array([0.05, 0.02, 0.03, 0.05])  # m beyond the listed extremes

# probability of each style of a multi-population kind (a US-heavy mix, as in AV2/nuScenes)
STYLE_WEIGHTS = {"tractor": {"cabover": 0.35, "conventional": 0.65},
                 "semi_trailer": {"eu": 0.35, "us": 0.57, "us_pup": 0.08}}


def _table(kind: str, style: str) -> np.ndarray:
    if kind not in FLEET_MODELS:
        raise ConfigError(f"no fleet statistics for kind {kind!r}")
    groups = FLEET_MODELS[kind]
    if style not in groups:
        raise ConfigError(f"kind {kind!r} has no style {style!r}; choose from {list(groups)}")
    return np.array([row[2:] for row in groups[style]], dtype=np.float64) / 1000.0


def dimension_stats(kind: str, style: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Mean (4,) and covariance (4, 4) of (length, width, height, wheelbase) in m."""
    t = _table(kind, style)
    cov = np.cov(t, rowvar=False)
    sd = np.sqrt(np.diag(cov))
    floor = np.maximum(sd, _MIN_SD)
    corr = cov / np.outer(sd, sd).clip(1e-12)
    np.fill_diagonal(corr, 1.0)
    return t.mean(axis=0), corr * 0.9 * np.outer(floor, floor) + 0.1 * np.diag(floor**2)


def dimension_bounds(kind: str) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper (4,) bounds (m) of the sampled (length, width, height, wheelbase)."""
    t = np.concatenate([_table(kind, s) for s in FLEET_MODELS[kind]])
    return t.min(axis=0) - _MARGIN, t.max(axis=0) + _MARGIN


def styles(kind: str) -> tuple[str, ...]:
    """Style keys of ``kind`` (``("",)`` for single-population kinds)."""
    return tuple(FLEET_MODELS[kind])


def sample_style(kind: str, rng: np.random.Generator) -> str:
    """Draw one style of ``kind`` with `STYLE_WEIGHTS` (uniform if not listed)."""
    keys = styles(kind)
    if len(keys) == 1:
        return keys[0]
    w = np.array([STYLE_WEIGHTS.get(kind, {}).get(k, 1.0) for k in keys])
    return keys[int(rng.choice(len(keys), p=w / w.sum()))]


def sample_dimensions(kind: str, rng: np.random.Generator, style: str = "") -> np.ndarray:
    """(4,) length, width, height, wheelbase (m) of one vehicle of ``kind`` (and ``style``).

    Multivariate normal fitted to the kind's listed models, truncated to the bounds of that
    style's models (plus a small margin) by rejection.
    """
    mean, cov = dimension_stats(kind, style)
    t = _table(kind, style)
    lo, hi = t.min(axis=0) - _MARGIN, t.max(axis=0) + _MARGIN
    chol = np.linalg.cholesky(cov)
    for _ in range(200):
        x = mean + chol @ rng.standard_normal(4)
        if np.all(x >= lo) and np.all(x <= hi):
            return x
    return np.clip(mean, lo, hi)
