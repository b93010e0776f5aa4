"""Object association (paper 000): keyframe groups, MOT inside a group, HDP across groups, Eq. 4-6."""
