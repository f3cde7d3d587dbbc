# Offline check behind docs/evidence/cooperation.md "Corners on an image pyramid for
# loop closures across lenses (stop 96)": ORB matches between rendered images of two
# robots whose cameras were near, counted correct against the true epipolar geometry.
# Needs opencv-python-headless, numpy, scipy, pyyaml (not project dependencies).
# Usage: python3 xlens_orb_pairs.py SEQUENCES A B FEATURES MODES, e.g.
#   python3 xlens_orb_pairs.py out/live-fleet/sequences 0 1 200 single,foc180,uni180,top180,pyr8
import numpy as np, cv2, yaml, sys, random
from scipy.spatial.transform import Rotation as Rot
base=sys.argv[1]
def load(i):
    d=f'{base}/seq{i}/mav0'
    y=open(f'{d}/cam0/sensor.yaml').read().replace('%YAML:1.0','')
    s=yaml.safe_load(y)
    T=np.array(s['T_BS']['data']).reshape(4,4)
    gt=np.loadtxt(f'{d}/state_groundtruth_estimate0/data.csv',delimiter=',')
    ims=[l.strip().split(',') for l in open(f'{d}/cam0/data.csv') if not l.startswith('#')]
    gtd={int(r[0]):r for r in gt}
    frames=[]
    for t,f in ims:
        r=gtd.get(int(t))
        if r is None: continue
        R=Rot.from_quat([r[5],r[6],r[7],r[4]]).as_matrix()
        Rc=R@T[:3,:3]; pc=r[1:4]+R@T[:3,3]
        frames.append((int(t),f'{d}/cam0/data/{f}',Rc,pc))
    K=np.array([[s['intrinsics'][0],0,s['intrinsics'][2]],[0,s['intrinsics'][1],s['intrinsics'][3]],[0,0,1]])
    return dict(frames=frames,K=K,D=np.array(s['distortion_coefficients']),model=s['distortion_model'],f=s['intrinsics'][0])
def undist(cam,pts):
    p=np.array(pts,dtype=np.float64).reshape(-1,1,2)
    if cam['model']=='equidistant':
        return cv2.fisheye.undistortPoints(p,cam['K'],cam['D']).reshape(-1,2)
    return cv2.undistortPoints(p,cam['K'],cam['D']).reshape(-1,2)
def feats(path,mode,n,cam):
    if mode.startswith('uni') or mode.startswith('top'):
        img=cv2.equalizeHist(cv2.imread(path,0))
        lv=max(1,1+int(np.floor(np.log(cam['f']/float(mode[3:]))/np.log(1.2)+1e-9)))
        ks=list(range(lv)) if mode.startswith('uni') else [lv-1]
        kps=[];des=[]
        for k in ks:
            s=1.2**k
            im=img if k==0 else cv2.resize(img,(round(img.shape[1]/s),round(img.shape[0]/s)),interpolation=cv2.INTER_AREA)
            orb=cv2.ORB_create(nfeatures=n//len(ks),nlevels=1,edgeThreshold=19,fastThreshold=20,patchSize=31)
            kk,dd=orb.detectAndCompute(im,None)
            if dd is None: continue
            for p in kk: kps.append(cv2.KeyPoint(p.pt[0]*s,p.pt[1]*s,31*s))
            des.append(dd)
        return kps,(np.vstack(des) if des else None)
    img=cv2.equalizeHist(cv2.imread(path,0))
    lv={'single':1,'pyr8':8,'pyr6':6}.get(mode) or max(1,1+int(np.floor(np.log(cam['f']/float(mode[3:]))/np.log(1.2)+1e-9)))
    orb=cv2.ORB_create(nfeatures=n,scaleFactor=1.2,nlevels=lv,edgeThreshold=19,fastThreshold=20,patchSize=31)
    kps,des=orb.detectAndCompute(img,None)
    return kps,des
def correct(camA,camB,fa,fb,kA,kB,matches):
    if not matches: return 0
    RA,pA=fa[2],fa[3]; RB,pB=fb[2],fb[3]
    R=RA.T@RB; t=RA.T@(pB-pA)  # B in A
    tx=np.array([[0,-t[2],t[1]],[t[2],0,-t[0]],[-t[1],t[0],0]]); E=tx@R
    xa=undist(camA,[kA[m.queryIdx].pt for m in matches]); xb=undist(camB,[kB[m.trainIdx].pt for m in matches])
    ok=0
    for a,b in zip(xa,xb):
        a3=np.array([a[0],a[1],1.]); b3=np.array([b[0],b[1],1.])
        Eb=E@b3; Ea=E.T@a3; num=(a3@E@b3)**2
        den=Eb[0]**2+Eb[1]**2+Ea[0]**2+Ea[1]**2
        if num/den < (3.0/min(camA['f'],camB['f']))**2: ok+=1
    return ok
A=int(sys.argv[2]); B=int(sys.argv[3]); n=int(sys.argv[4])
ca,cb=load(A),load(B)
pairs=[]
for fa in ca['frames'][::5]:
    for fb in cb['frames'][::5]:
        if np.linalg.norm(fa[3]-fb[3])<0.4 and np.degrees(np.arccos(np.clip(fa[2][:,2]@fb[2][:,2],-1,1)))<20:
            pairs.append((fa,fb))
random.seed(1); random.shuffle(pairs); pairs=pairs[:25]
print(f'seq{A} vs seq{B}: {len(pairs)} pairs, {n} features')
bf=cv2.BFMatcher(cv2.NORM_HAMMING,crossCheck=True)
for mode in sys.argv[5].split(','):
    res=[]
    for fa,fb in pairs:
        kA,dA=feats(fa[1],mode,n,ca); kB,dB=feats(fb[1],mode,n,cb)
        if dA is None or dB is None: res.append((0,0)); continue
        m=[x for x in bf.match(dA,dB) if x.distance<50]
        res.append((len(m),correct(ca,cb,fa,fb,kA,kB,m)))
    r=np.array(res)
    print(f'{mode:7s} matches {r[:,0].mean():6.1f}  correct mean {r[:,1].mean():5.1f} median {np.median(r[:,1]):5.1f} max {r[:,1].max()}  pairs>=15 correct {np.sum(r[:,1]>=15)}/{len(r)}')
