"""What crosses between the world, the robots and the evaluator, as plain data: sensor
readings, keyframe measurements, the team stream's records and their wire form, the numeric
wire path (times, quaternions, dead reckoning). Both sides import it; it imports no other
subpackage of core."""
