"""`esr play`: a person in the human's seat with a trained robot, in a terminal or a browser.

game.py     the one game loop (keys -> human actions, the robot's policy, the episode's end)
session.py  the study (counterbalanced robots, neutral labels) and its `play` artifacts
terminal.py the terminal front end; web.py the browser front end (docs/play.md)
"""
