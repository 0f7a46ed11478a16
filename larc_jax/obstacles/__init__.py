"""Obstacles and their distance lower bounds."""
