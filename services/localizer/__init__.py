"""localizer: LiDAR localization from plane and edge features after seed 003's Grape system (sec. 2.1)."""
