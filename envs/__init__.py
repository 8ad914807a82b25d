"""The Gymnasium side of crowdnav-mesrnn: pymunk world, crowds, observation, reward, rendering."""
