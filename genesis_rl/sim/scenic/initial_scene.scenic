"""GENESIS-RL's initial scene, as the paper generates it with Scenic.

The ego on a lane that has a lane to its right going the same way, a lead ahead of it in its lane, a
neighbour ahead in the lane to its right, and candidates for the others on roads within a radius of the
ego, with makes and colours drawn from GENESIS-RL's catalog vocabulary. The candidates may overlap: the
generator keeps them in Scenic's order while they fit (27 cars placed at once with no overlap would almost
never survive Scenic's rejection sampling). Parameters (set by genesis-rl scenes --generator scenic): map
(an OpenDRIVE file), others (candidates), radius [m], makes, make_weights, ego_makes, colors, lane_width [m].
"""
param map = localPath('urban.xodr')
model scenic.domains.driving.model

param others = 80
param radius = 90
param makes = ['sedan']
param make_weights = [1]
param ego_makes = ['sedan']
param colors = ['white']
param lane_width = 3.5

egoSections = [s for s in network.laneSections if s._laneToRight is not None and s.centerline.length > 60]
egoSection = Uniform(*egoSections)

ego = new Car on egoSection.centerline,
    with genesis_role 'ego',
    with genesis_make Uniform(*globalParameters.ego_makes),
    with genesis_color Uniform(*globalParameters.colors)

lead = new Car following roadDirection from ego for Range(15, 40),
    with genesis_role 'lead',
    with genesis_make Discrete({m: w for m, w in zip(globalParameters.makes, globalParameters.make_weights)}),
    with genesis_color Uniform(*globalParameters.colors)

neighbour = new Car following roadDirection from (ego offset by (globalParameters.lane_width, 0)) for Range(6, 20),
    with genesis_role 'neighbour',
    with genesis_make Discrete({m: w for m, w in zip(globalParameters.makes, globalParameters.make_weights)}),
    with genesis_color Uniform(*globalParameters.colors)

near = network.roadRegion.intersect(CircularRegion(ego.position, globalParameters.radius))
for i in range(globalParameters.others):
    new Car on near,
        with allowCollisions True,
        with regionContainedIn everywhere,
        with genesis_role 'other',
        with genesis_make Discrete({m: w for m, w in zip(globalParameters.makes, globalParameters.make_weights)}),
        with genesis_color Uniform(*globalParameters.colors)
