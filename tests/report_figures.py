"""Prints the oracle figures quoted in the issue note: python tests/report_figures.py (about 1 min)."""
import sys, math; import os; sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import numpy as np, jax, jax.numpy as jnp
import pcrjax
from helpers import rod_scene
from oracles import *
from pcrjax.bdf_alpha import amplification
L,R,E=0.4,1e-3,207e9; EI=E*math.pi*R**4/4
res=pcrjax.solve_static(rod_scene(force=(0,0,-1e-3),nodes=20,effects={"inertia":False}))
print("EB rel err", -float(res.position[2])/euler_bernoulli_tip(1e-3,L,E,R)-1)
ref=elastica_tip(1.0)
for se in (False,True):
    r=pcrjax.solve_static(rod_scene(force=(0,0,-EI/L**2),nodes=64,effects={"inertia":False,"shear_extension":se}))
    p=np.asarray(r.position); t=np.asarray(r.rotation)[:,2]
    got=(-p[2]/L,1-p[0]/L,math.atan2(-t[2],t[0]))
    print("elastica", "cosserat" if se else "kirchhoff", got, "rel", [g/x-1 for g,x in zip(got,ref)])
for integ,Ns in (("rk4",[8,16,32]),("euler",[16,32,64])):
    P=0.5*EI/L**2
    rr=pcrjax.solve_static(rod_scene(force=(0,0,-P),nodes=512,effects={"inertia":False}))
    e=[float(np.linalg.norm(np.asarray(pcrjax.solve_static(rod_scene(force=(0,0,-P),nodes=N,integrator=integ,effects={"inertia":False})).position)-np.asarray(rr.position))) for N in Ns]
    print(integ, Ns, e, "orders", [math.log2(e[i]/e[i+1]) for i in range(len(e)-1)])
F1=first_frequency_hz(L,E,R,8000.); W1=2*math.pi*F1
dt=0.05/W1; tr=pcrjax.simulate(rod_scene(force=(0,0,-1e-3),nodes=40,dt=dt,alpha=-0.5,duration=1.2))
(w1,_),_=fit_sinusoids(np.asarray(tr.t),np.asarray(tr.position)[:,2],[W1,6.27*W1])[0]
print("freq Hz", w1/2/math.pi, "rel to 8.895", w1/2/math.pi/8.895-1)
for a,expct in [(-0.5,1.0),(-0.4,0.981),(-0.2,0.935),(0.0,0.886)]:
    dt=0.5/W1; P=22 if a==-0.5 else 12
    tr=pcrjax.simulate(rod_scene(force=(0,0,-1e-3),nodes=20,dt=dt,alpha=a,duration=P/F1)); t=np.asarray(tr.t); z=np.asarray(tr.position)[:,2]
    sk=t>2/F1; (w1,_),(w2,_)=fit_sinusoids(t[sk],z[sk],[0.97*W1,3/dt])[0]
    c,amp=window_amplitudes(t[sk],z[sk],w1,[w2]); sl=np.polyfit(c*F1,np.log(amp),1)[0]
    print("bdf alpha", a, "ratio/period", math.exp(sl), "expected", expct, "theory", abs(amplification(0.5,a))**(2*math.pi/0.5), "20-period", math.exp(20*sl) if a==-0.5 else "")
